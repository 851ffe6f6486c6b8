"""The server's public pages, rendered to HTML: the leaderboard, a submission's page, a team's public page. Every
table goes through `dsr_bench.leaderboard.table.render_table`, the code that renders the local leaderboard's; every
name is HTML-escaped. The team's own pages and the participants' guide are `team_pages`.
"""

from __future__ import annotations

import html
from typing import Any
from urllib.parse import quote

from dsr_bench.challenge.layout import part_title
from dsr_bench.leaderboard.table import COLUMN_TITLES, LINKS, ROLE, SORT_SCRIPT, TRACKS as COLUMNS, render_table

#: the pages' style: tables fit 1400 px (names and notes wrap at spaces, numbers, dates and checksums do not)
STYLE = ("body{font-family:sans-serif;margin:1.5em}p,ul,ol,pre,h1{max-width:80em}table{border-collapse:collapse;"
         "margin:1em 0;font-size:.92em}td,th{border:1px solid #bbb;padding:.25em .45em;text-align:right}"
         "td[data-v],table.board td:nth-last-child(-n+3){white-space:nowrap}"
         "td:not([data-v]),th:first-child{text-align:left;overflow-wrap:break-word}"
         "th{cursor:pointer;background:#f4f4f4}.best{font-weight:bold}.worse{color:#a00}.note{color:#555}"
         ".state{font-weight:bold}nav a{margin-right:1em}.error{color:#a00;font-weight:bold}"
         "form.inline{display:inline;margin:0}code{overflow-wrap:anywhere}")
#: the links at the top of every page
NAV = ('<nav><a href="/">leaderboard</a><a href="/participate">how to take part</a>'
       '<a href="/me">your submissions</a></nav>')
#: the breakdowns shown on a submission's page, titled as `dsr-bench evaluate` prints them
BREAKDOWNS = (("iou_occluded_objects", "IoU of mostly occluded objects", "occluded_object_steps"),
              ("iou_visible_objects", "IoU of visible objects", "visible_object_steps"),
              ("motion_moved_objects", "flow MSE of moved objects (cm²)", ""),
              ("motion_static_objects", "flow MSE of static objects (cm²)", ""))
#: the leaderboard table's columns before the method: the rank and the team (linked to its page)
LEAD = (("#", "rank"), ("team", "team"))


def page(title: str, body: str, refresh: bool = False) -> str:
    """A whole page: `body` under the navigation links, with the style and the tables' sort script."""
    meta = '<meta http-equiv="refresh" content="2">' if refresh else ""
    return (f'<!doctype html><html lang="en"><head><meta charset="utf-8">{meta}<title>{html.escape(title)}</title>'
            f'<meta name="viewport" content="width=device-width"><style>{STYLE}</style></head><body>{NAV}{body}'
            f"<script>{SORT_SCRIPT}</script></body></html>")


def link(text: str, href: str) -> str:
    """A link, both escaped."""
    return f'<a href="{html.escape(href)}">{html.escape(text)}</a>'


def team_href(name: str) -> str:
    """A team's public page."""
    return f"/teams/{quote(str(name), safe='')}"


def _columns(track: str, rows: list[dict]) -> list[str]:
    """The track's columns (the local leaderboard's) that some row of the table has a value of."""
    return [c for c in COLUMNS.get(track, ()) if any(has_value(r.get(c)) for r in rows)]


def has_value(value: Any) -> bool:
    """Whether `value` is a number to show (not a bool, not NaN)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and value == value


def table(rows: list[dict], track: str, lead: tuple[tuple[str, str], ...] = ()) -> str:
    """An HTML table of rows in `dsr_bench.leaderboard.table`'s shape, rendered by its `render_table`: the very code
    that renders the local leaderboard's tables (every text cell escaped)."""
    return render_table(rows, track, _columns(track, rows), lead=lead).html("board")


def submission_row(row: dict, rank: int | None = None) -> dict:
    """A scored submission (`service.leaderboard` or `final_ranking` row) as a table row: no model grid or split
    checksum (a submission's page shows its hidden part's); its phase and final choice as the note."""
    note = ", ".join(n for n in (f"phase {row['phase']}" if row.get("phase") else "",
                                 "final" if row.get("final") else "") if n)
    return {**row["metrics"], "rank": "" if rank is None else str(rank), "team": row.get("team", ""),
            "method": row["method"], "grid": "-", "label": note, "toolkit": row.get("toolkit_version") or "",
            "date": row.get("date", ""), "checksum": "", ROLE: "submission",
            LINKS: {"team": team_href(str(row.get("team", ""))), "method": f"/submissions/{row['id']}"}}


def _server_reference_row(row: dict) -> dict:
    """A reference row the server scored on the hidden set (`service.server_references`) as a table row: marked
    among the server's reference rows only (its own role), linked to its submission's page."""
    return {**row["metrics"], "rank": "", "team": "", "method": row["method"], "grid": "-",
            "label": "reference, scored by this server on the hidden set", "toolkit": row.get("toolkit_version") or "",
            "date": row.get("date", ""), "checksum": "", ROLE: "hidden-reference",
            LINKS: {"method": f"/submissions/{row['id']}"}}


def _hidden_references(data: dict, name: str, part: str) -> dict[str, list[dict]]:
    """Per track, the table rows of the reference rows the server scored on hidden set `name`'s `part`."""
    found = (data.get("hidden_references") or {}).get(name, {}).get(part, {})
    return {track: [_server_reference_row(r) for r in rows] for track, rows in found.items()}


def _reference_note(shown: str, split: str) -> str:
    same = "" if shown == split else f" (generated with the same settings as {html.escape(split)})"
    return (f"<p class=note>Reference rows (unranked, below the submissions): the local leaderboard's static, push "
            f"and oracle rows of {html.escape(shown)}{same}, scored by <code>dsr-bench evaluate</code> on that "
            "split's pinned public sequences, not on this challenge's hidden ones (drawn with the split's objects "
            "and policy from a secret seed): a yardstick, not a paired comparison. Bold and &#9660; mark the "
            "reference rows among themselves, as on the local leaderboard; submissions, ranked by #, are never "
            "marked against them.</p>")


def render_leaderboard(data: dict, config: dict, references: dict[str, list[dict]] | None = None,
                       reference_split: str | None = None) -> str:
    """The leaderboard page: per track the public part's table with the `references` rows per track (of
    `reference_split`: `service.reference_rows`) beside the submissions, the final ranking once revealed, the
    phases."""
    references = references or {}
    parts = [f"<h1>{html.escape(str(config.get('title') or 'DSR benchmark challenge'))}</h1>"]
    phase, closed = data.get("open") or (None, None)
    parts.append(f"<p>{html.escape(closed or (f'phase {phase} is open' if phase else 'submissions are open'))}; "
                 f"{html.escape(str(config['daily_limit']))} submissions per team per day. "
                 f'{link("How to take part", "/participate")}.</p>')
    if references:
        parts.append(_reference_note(str(reference_split), str(config.get("split", ""))))
    if any(rows for by_part in (data.get("hidden_references") or {}).values() for rows in by_part.values()):
        parts.append("<p class=note>Rows noted <i>scored by this server on the hidden set</i> are the host's "
                     "reference models (<code>dsr-bench challenge add-references</code>), predicted on the same "
                     "inputs as the submissions and scored by the same workers; bold and &#9660; mark them among "
                     "themselves.</p>")
    sets = [("simulated", "", data)] + [(name, f", hidden set {name} ({entry.get('source') or 'further'} sequences)",
                                         entry) for name, entry in sorted((data.get("hidden_sets") or {}).items())]
    for name, title, entry in sets:
        local = references if name == "simulated" else {}
        if entry.get("final"):
            private = _hidden_references(data, name, "private")
            for track, rows in sorted(entry["final"].items()):
                parts.append(f"<h2>Final ranking, {html.escape(track)} track{html.escape(title)} (private part)</h2>")
                parts.append(table([submission_row(r, i) for i, r in enumerate(rows, 1)] + private.get(track, [])
                                   + local.get(track, []), track, LEAD))
        public = _hidden_references(data, name, "public")
        for track in sorted(set(entry["tracks"]) | set(local) | set(public)):
            rows = entry["tracks"].get(track, [])
            parts.append(f"<h2>{html.escape(track)} track{html.escape(title)} (public part), ranked by "
                         f"{html.escape(COLUMN_TITLES.get(config['rank_by'].get(track, ''), ''))}</h2>")
            parts.append(table([submission_row(r, i) for i, r in enumerate(rows, 1)] + public.get(track, [])
                               + local.get(track, []), track, LEAD))
    if not data["tracks"]:
        parts.append("<p>No scored submission yet.</p>")
    if data.get("phases"):
        items = "".join(f"<li>{html.escape(p['name'])}: {html.escape(p['start'])} to {html.escape(p['end'])}</li>"
                        for p in data["phases"])
        parts.append(f"<h2>Phases</h2><ul>{items}</ul>")
    return page("Leaderboard", "".join(parts))


def _score_tables(view: dict, part: str, score: dict, checksum: str) -> list[str]:
    """A part's tables on a submission's page: per track scored (3D, and 2D where the 2D flow was scored) its
    columns, with the toolkit and the part's split checksum, then its breakdowns."""
    metrics = score.get("metrics", {})
    row = {**metrics, "method": view["method"], "grid": "-", "label": part_title(part),
           "toolkit": score.get("toolkit_version") or "", "date": str(score.get("scored_at", ""))[:10],
           "checksum": checksum, ROLE: "submission"}
    tracks = [t for t in ("3D", "2D") if any(has_value(metrics.get(c)) for c in COLUMNS.get(t, ()))]
    out = [f"<h3>{html.escape(track)} track</h3>" + table([row], track) for track in tracks]
    breakdowns = score.get("breakdowns") or {}
    cells = []
    for key, title, count in BREAKDOWNS:
        if key in breakdowns:
            value = breakdowns[key]
            text = f"{value:.4f}" if has_value(value) else "-"
            n = f" ({breakdowns[count]} object-steps)" if count and count in breakdowns else ""
            cells.append(f"<tr><td>{html.escape(title + n)}</td><td data-v>{html.escape(text)}</td></tr>")
    if cells:
        out.append(f"<h3>Breakdowns</h3><table><tbody>{''.join(cells)}</tbody></table>")
    coverage = score.get("coverage") or {}
    if coverage:
        out.append(f"<p class=note>{coverage.get('scored')} of {coverage.get('expected')} sequences scored; "
                   f"predictions' checksum <code>{html.escape(str(score.get('predictions_checksum', ''))[:12])}"
                   "</code></p>")
    return out


def render_submission(view: dict, checksums: dict[str, str] | None = None) -> str:
    """A submission's page: who sent it, its state (reloading every 2 s until scored, refused or failed), why it was
    refused or failed, per part shown its tables (`_score_tables`; `checksums`: per part the hidden part's split
    checksum, 12 hex digits), and its result file."""
    checksums = checksums or {}
    waiting = view["state"] in ("queued", "running")
    sid = view["id"]
    team = str(view["team"])
    flags = ", ".join(f for f in (f"phase {view['phase']}" if view.get("phase") else "",
                                  "chosen as final" if view.get("final") else "") if f)
    parts = [f"<h1>Submission {html.escape(sid)}</h1>",
             f"<p>team {link(team, team_href(team))}, method {html.escape(view['method'])}, submitted "
             f"{html.escape(view['created'])}{html.escape(', ' + flags if flags else '')}</p>",
             f'<p>state: <span class="state" id="state">{html.escape(view["state"])}</span></p>']
    if view["messages"]:
        why = {"refused": "Why it was refused", "failed": "Why it failed"}.get(view["state"], "Messages")
        parts.append(f"<h2>{why}</h2><ul id=messages>"
                     + "".join(f"<li>{html.escape(m)}</li>" for m in view["messages"]) + "</ul>")
        if view["state"] == "refused":
            parts.append("<p class=note>Check predictions before submitting with <code>dsr-bench evaluate</code> "
                         "on a public split; a refused submission does not use one of the day's tries.</p>")
    for part, score in sorted(view["scores"].items(), key=lambda item: ("-" in item[0], item[0])):
        parts.append(f"<h2>{html.escape(part_title(part))}</h2>")
        parts += _score_tables(view, part, score, checksums.get(part, ""))
    if not waiting:
        parts.append(f"<p>{link('result file (JSON)', f'/api/submissions/{sid}/result')}</p>")
    parts.append(f"<p>{link('leaderboard', '/')} &middot; {link('team ' + team, team_href(team))}</p>")
    return page(f"Submission {sid}", "".join(parts), refresh=waiting)


def render_team(name: str, views: list[dict]) -> str:
    """A team's public page: its scored submissions and their public aggregate scores."""
    rows = [{**v["scores"].get("public", {}).get("metrics", {}), "method": v["method"], "grid": "-",
             "label": "final" if v["final"] else "", "date": v["created"][:10],
             "toolkit": v["scores"].get("public", {}).get("toolkit_version") or "", ROLE: "submission",
             LINKS: {"method": f"/submissions/{v['id']}"}} for v in views]
    body = [f"<h1>Team {html.escape(name)}</h1>",
            table(rows, views[0].get("track") or "3D") if rows else "<p>No scored submission yet.</p>",
            f"<p>{link('leaderboard', '/')}</p>"]
    return page(f"Team {name}", "".join(body))

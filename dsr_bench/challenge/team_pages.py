"""The participants' pages, rendered to HTML: signing in with the team's token, the team's own page (every
submission, its state, why it was refused or failed, its result file, the final choices) and the guide (how to
download the inputs, predict, submit and choose finals). Every name is HTML-escaped; every form that changes
something carries the session's CSRF token (`auth.SessionSigner.csrf_token`).
"""

from __future__ import annotations

import html

from dsr_bench.challenge.pages import has_value, link, page
from dsr_bench.leaderboard.table import COLUMN_TITLES, LOWER_IS_BETTER


def render_login(error: str = "") -> str:
    """The sign-in form: the team's token, posted to /login (never put in a URL)."""
    shown = f'<p class="error" id="error">{html.escape(error)}</p>' if error else ""
    return page("Sign in", (
        "<h1>Sign in with your team's token</h1>" + shown +
        '<form method="post" action="/login"><p><label>token <input type="password" name="token" id="token" '
        'size="70" autocomplete="current-password" required></label> <button type="submit" id="sign-in">sign in'
        "</button></p></form><p class=note>The token the host sent your team (<code>dsrc_...</code>). Signing in "
        "keeps a session cookie for 12 hours (HttpOnly, SameSite=Strict); it shows your submissions, their reasons "
        "and result files, and lets you choose your final ones.</p>"))


def _hidden(name: str, value: str) -> str:
    return f'<input type="hidden" name="{name}" value="{html.escape(value)}">'


def _final_form(sid: str, final: bool, csrf: str) -> str:
    label = "unselect" if final else "choose as final"
    return (f'<form class="inline" method="post" action="/me/final">{_hidden("sid", sid)}'
            f'{_hidden("final", "0" if final else "1")}{_hidden("csrf", csrf)}'
            f'<button type="submit" id="final-{html.escape(sid)}">{label}</button></form>')


def _value(view: dict, part: str, key: str) -> str:
    value = view["scores"].get(part, {}).get("metrics", {}).get(key)
    return f"{value:.4f}" if has_value(value) else ""


def render_history(team: str, views: list[dict], status: dict, csrf: str, error: str = "") -> str:
    """The team's own page: its submissions newest first (state, the ranking metric on the public part and, once
    revealed, the private one, why a refused or failed one was, its result file, its final choice with a button),
    and `status`: "tries" used today, "daily_limit", "finals" chosen, "max_final", "rank_by" ({track: metric}),
    "revealed", "submissions_closed" and "finals_closed" (a reason or None)."""
    parts = [f"<h1>Team {html.escape(team)}: your submissions</h1>"]
    if error:
        parts.append(f'<p class="error" id="error">{html.escape(error)}</p>')
    closed = status.get("submissions_closed")
    parts.append(f"<p id=quota>{status['tries']} of {status['daily_limit']} submissions used today (UTC; refused and "
                 f"failed ones do not count); {status['finals']} of {status['max_final']} final submissions chosen"
                 "; none chosen: your newest scored one counts.</p>")
    for reason in dict.fromkeys(r for r in (closed, status.get("finals_closed")) if r):
        parts.append(f"<p class=note>{html.escape(reason)}.</p>")
    revealed = bool(status.get("revealed"))
    rank_by = status.get("rank_by") or {}
    heads = ["submitted", "method", "state", "track", "public part", *(["private part"] if revealed else []),
             "final", "result", "why refused or failed"]
    rows = []
    for v in views:
        key = rank_by.get(v.get("track") or "", "")
        title = COLUMN_TITLES.get(key, key)
        arrow = " (lower is better)" if key in LOWER_IS_BETTER else ""
        public = _value(v, "public", key)
        cells = [html.escape(v["created"].replace("T", " ").rstrip("Z")), link(v["method"], f"/submissions/{v['id']}"),
                 f'<span class="state">{html.escape(v["state"])}</span>', html.escape(v.get("track") or ""),
                 html.escape(f"{public} {title}{arrow}" if public else "")]
        if revealed:
            private = _value(v, "private", key)
            cells.append(html.escape(f"{private} {title}" if private else ""))
        final = "final " if v["final"] else ""
        form = _final_form(v["id"], v["final"], csrf) if v["state"] == "scored" and not status.get(
            "finals_closed") else ""
        cells.append(html.escape(final) + form)
        cells.append(link("JSON", f"/api/submissions/{v['id']}/result") if v["state"] in ("scored", "refused",
                                                                                          "failed") else "")
        cells.append(html.escape(v["messages"][0] + (f" (and {len(v['messages']) - 1} more)" if len(
            v["messages"]) > 1 else "")) if v["state"] in ("refused", "failed") and v["messages"] else "")
        rows.append(f'<tr id="row-{html.escape(v["id"])}">' + "".join(f"<td>{c}</td>" for c in cells) + "</tr>")
    if rows:
        parts.append("<table id=history><thead><tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in heads)
                     + f"</tr></thead><tbody>{''.join(rows)}</tbody></table>")
    else:
        parts.append(f"<p>No submission yet: {link('how to take part', '/participate')}.</p>")
    parts.append(f'<form method="post" action="/logout">{_hidden("csrf", csrf)}<button type="submit" '
                 'id="sign-out">sign out</button></form>')
    return page(f"Team {team}", "".join(parts))


def render_participate(server: str, config: dict, phases: list[dict], closed: str | None) -> str:
    """The participants' guide: download the inputs, predict, check, submit, follow, choose the final submissions;
    the rules (quota, finals, phases, the end) with this challenge's numbers, `server` the URL to give."""
    e = html.escape
    limit, finals = e(str(config["daily_limit"])), e(str(config["max_final"]))
    size = int(config["max_upload_bytes"]) / (1 << 20)
    listed = "".join(f"<li>{e(p['name'])}: {e(p['start'])} to {e(p['end'])} (UTC)</li>" for p in phases)
    rank = ", ".join(f"{e(track)}: {e(COLUMN_TITLES.get(key, key))}"
                     for track, key in sorted(config["rank_by"].items()))
    body = f"""<h1>How to take part</h1>
<p>{e(closed or "Submissions are open.")}</p>
<ol>
<li><b>Get the toolkit and your token.</b> <code>pip install 'dsr-bench[challenge]'</code> (or a clone's
<code>bash scripts/setup.sh</code>); the host sends your team a token <code>dsrc_...</code>: keep it secret, and give
it as <code>--token</code> or in <code>$DSR_BENCH_TOKEN</code>.</li>
<li><b>Download the inputs</b> (observations and actions only; each file checked against its digest):
<pre>dsr-bench challenge download inputs --server {e(server)}</pre></li>
<li><b>Predict</b> one file per sequence, with your model or a toolkit one:
<pre>dsr-bench predict --model static --data inputs --out predictions</pre>
Check your predictions' format on a public split first with <code>dsr-bench evaluate</code>: every file 3D (mask and
motion, optionally motion_2d) or every file 2D-only (motion_2d alone), never a mix.</li>
<li><b>Submit</b> and follow it until scored:
<pre>dsr-bench submit predictions --server {e(server)} --token $DSR_BENCH_TOKEN --method "my method"</pre>
It prints the public part's scores (exit 0), or each problem as <code>dsr-bench evaluate</code> prints it (exit 1);
an upload the server refuses (token, quota, closed, too large) is one line and exit 2. <code>--final</code> also
chooses it as one of your final submissions once scored.</li>
<li><b>Choose your final submissions</b> (at most {finals}; none chosen: your newest scored one), on
{link("your page", "/me")} or with
<pre>dsr-bench challenge final --server {e(server)}              # lists yours
dsr-bench challenge final SUBMISSION_ID --server {e(server)}  # chooses one (--undo: unselects it)</pre></li>
</ol>
<h2>Rules</h2>
<ul>
<li>{limit} submissions per team per UTC day; a refused submission (a missing or unreadable file) or one the server
failed on does not use one; uploads in all, refused ones included, are limited to four times as many.</li>
<li>Uploads up to {size:.0f} MiB; the phase is checked when an upload is stored: one still arriving when the phase
ends is refused.</li>
<li>Ranked by {rank}. The leaderboard shows the public part's scores; the private part's, which make the final
ranking, are shown to nobody, your team included, until the host reveals them at the end.</li>
<li>Final choices can change until the last phase ends; the reveal ends the challenge: submissions and final choices
close.</li>
<li>Team and method names: 1-64 visible characters; a name that reads like another one (case, look-alike letters,
spacing aside) is refused.</li>
</ul>
{f"<h2>Phases</h2><ul>{listed}</ul>" if listed else ""}"""
    return page("How to take part", body)

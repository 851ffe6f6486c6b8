"""One table renderer for every leaderboard table: the local leaderboard's README.md and index.html (`board.build`)
and the challenge server's pages (`dsr_bench.challenge.server`) render their rows through `render_table`.

A row is a mapping in `board.load_rows`'s shape: "method", "grid", "label", "toolkit", "date", "checksum", the
values of its metric columns (`COLUMN_TITLES`' keys; None or NaN: no value) and, optionally, its per-unit values
under `SEQ` ({sequence or task: {column: value}}), from which each cell's 95% interval is computed, links under
`LINKS`, the reference row it is by provenance under `REFERENCE` (`board.load_rows` sets it from
`provenance.reference_of`: "" for none) and its role under `ROLE` (a submission named like a reference row is not
one); only a row without either is a reference row by its name. Every text cell is escaped: HTML with
`html.escape`, markdown with `entries.markdown_cell`.
"""

from __future__ import annotations

import html
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from dsr_bench.leaderboard.entries import markdown_cell
from dsr_bench.leaderboard.names import fold
from dsr_bench.scoring.metrics import METRICS, TRACKS as METRIC_TRACKS, metric_keys
from dsr_bench.scoring.styles import is_reference_method
from dsr_bench.scoring.spread import Spread, paired_difference, spread, unit_values

#: each track's columns: its headline metrics (`dsr_bench.scoring.metrics.METRICS`), titled and ranked as they say
TRACKS = {track: metric_keys((track,), ("headline",)) for track in METRIC_TRACKS}
LOWER_IS_BETTER = {m.key for m in METRICS if m.role == "headline" and m.lower_is_better}
COLUMN_TITLES = {**{m.key: m.column for m in METRICS if m.column}, "planning_iou": "planning IoU"}
#: the script that sorts a table (`html_table`) by the column whose header is clicked; pages embed it
SORT_SCRIPT = (
    'function sortTable(th){\n'
    "  const table=th.closest('table'), i=[...th.parentNode.children].indexOf(th), body=table.tBodies[0];\n"
    "  const asc=th.dataset.asc!=='1'; th.dataset.asc=asc?'1':'0';\n"
    "  const key=r=>{const c=r.children[i]; const v=c.dataset.v; "
    "return v!==undefined&&v!==''?parseFloat(v):c.textContent;};\n"
    '  [...body.rows].sort((a,b)=>{const x=key(a),y=key(b); return (x>y?1:x<y?-1:0)*(asc?1:-1);})'
    '.forEach(r=>body.appendChild(r));\n'
    '}\n')

#: an HTML row's cell: (its HTML, text escaped; its sort value, or None; its CSS classes)
Cell = tuple[str, str | None, str]

#: the planning tables' reference row of not pushing at all (the tasks' start IoUs)
NO_PUSH = "no push (planning)"
#: where a row keeps its per-unit values ({sequence or task: {column: value}}), from which spread is computed
SEQ = "_per_unit"


_WORSE_MARK = "\u25bc"


#: Rows that bound the benchmark from above: never "best" (ground truth as predictions, or a model
#: warped with the ground-truth flow).
def is_oracle(method: str) -> bool:
    """Whether a row is an oracle: its method is `oracle` or says "oracle" (e.g. "GTWarp (oracle warp)", look-alike
    letters and case aside: `names.fold`), or it is GTWarp (`gtwarp`, `gtwarp-cpu`: its history is warped by the
    ground-truth flow)."""
    name = fold(method)
    return "oracle" in name or name.startswith("gtwarp")


#: The reference row every trained row must beat: predicting no motion.
NO_MOTION = "static"


#: where a row may say what it is: "submission" (a challenge's submitted row: never a reference row, whatever its
#: name) or "reference"; without it (and without `REFERENCE`) a row is a reference row by its name
#: (`is_reference_method`, `is_oracle`)
ROLE = "_role"
#: where a row says which reference row it is by provenance (`provenance.reference_of`: "static", "push", "oracle",
#: "random", "no push"; "" for none: then no name makes it one)
REFERENCE = "_reference"


def _submitted(row) -> bool:
    return ROLE in row and row[ROLE] == "submission"


def _provenance(row) -> str | None:
    """The reference row a row is by provenance ("" none), or None where the row does not say."""
    value = row[REFERENCE] if REFERENCE in row else None
    return None if value is None or value != value else str(value)  # NaN: a row of a frame that does not say


def is_oracle_row(row) -> bool:
    """Whether a row is an oracle (never best): the oracle reference row, or by its name (`is_oracle`: a name can
    only keep its own row from being ranked), unless it is a submission."""
    return not _submitted(row) and (_provenance(row) == "oracle" or is_oracle(row["method"]))


def is_reference_row(row) -> bool:
    """Whether a row is a reference row (static, push, oracle, random, no push): by its provenance where the row
    says it (`REFERENCE`), else by its name; a submission never is."""
    reference = _provenance(row)
    if reference is not None:
        return bool(reference)
    return not _submitted(row) and is_reference_method(row["method"])


def is_named(row, name: str) -> bool:
    """Whether a row is the reference row `name` (a submission, or a row that says it is no reference row, never
    is)."""
    return row["method"] == name and not _submitted(row) and _provenance(row) != ""


def named(table, name: str):
    """The table's rows that are the reference row `name` (`is_named`)."""
    return table[[is_named(r, name) for _, r in table.iterrows()]] if len(table) else table


def _best(table, column):
    """The best non-oracle value of a column, or None (no bold) when the table has no no-motion reference row
    of reproduced results: a best that cannot be compared with predicting no motion is not marked."""
    values = table[[not is_oracle_row(r) for _, r in table.iterrows()]][column].dropna()
    if values.empty:
        return None
    return values.min() if column in LOWER_IS_BETTER else values.max()


def _no_motion_values(table, columns: list[str]) -> dict[str, float | None]:
    """Per column, the value of the table's (first) no-motion reference row that has one, or None."""
    rows = named(table, NO_MOTION)
    return {c: (None if values.empty else values.iloc[0]) for c in columns for values in (rows[c].dropna(),)}


def _worse_than_no_motion(ref: float | None, column, row) -> bool:
    """Whether a trained row's value is worse than `ref`, the no-motion reference row's in the same table
    (`_no_motion_values`)."""
    if ref is None or is_named(row, NO_MOTION) or is_oracle_row(row) or row[column] != row[column]:
        return False
    return row[column] > ref if column in LOWER_IS_BETTER else row[column] < ref


def _decimals(value: float, column: str) -> int:
    """Decimals shown for a value of `column`: 3 for an IoU, else 4 significant digits."""
    if column.startswith(("iou", "planning")):
        return 3
    if value == 0 or value != value or math.isinf(value):
        return 0
    return max(0, 3 - math.floor(math.log10(abs(value))))


def _fmt(value, column, published: bool = False) -> str:
    """A value as shown: an IoU with 3 decimals, a flow MSE with 4 significant digits (0 as "0"; a `published`
    number as the paper prints it, at most 4 digits), "-" for none."""
    if value is None or value != value:
        return "-"
    if published and not column.startswith(("iou", "planning")):
        return f"{value:.4g}"
    return f"{value:.{_decimals(value, column)}f}"


def _plus_minus(value: float, half: float, column: str) -> str:
    """`half` (a spread's half-width or standard error) with the decimals of `value`, or 2 significant digits
    when `value` is 0."""
    if half != half:
        return ""
    digits = _decimals(value, column) if value else max(0, 1 - math.floor(math.log10(half))) if half > 0 else 0
    return f" \u00b1 {half:.{digits}f}"


def _spread_of(row, column) -> Spread:
    """The spread of a row's per-unit (sequence or task) values of `column`."""
    return spread(list(unit_values(row[SEQ], column).values()))


def _cell(row, column) -> str:
    """A metric's cell: the row's value and, where the row holds per-unit values, the half-width of its 95%
    interval over them."""
    text = _fmt(row[column], column)
    s = _spread_of(row, column)
    return text + (_plus_minus(row[column], s.half, column) if text != "-" and s.n >= 2 else "")


def _difference(d: Spread, column: str) -> str:
    """A paired difference's cell: its mean with sign and its standard error; "-" without two units."""
    if d.n < 2:
        return "-"
    digits = 3 if column.startswith(("iou", "planning")) else max(
        0, 1 - math.floor(math.log10(d.se))) if d.se > 0 else 3
    return f"{d.mean:+.{digits}f} \u00b1 {d.se:.{digits}f}"


def _yardsticks(table, track: str) -> list[str]:
    """The reference rows a table's rows are compared with, pairwise: static and push, or in a planning table
    no push and random."""
    names = (NO_PUSH, "random (planning)") if track == "planning" else (NO_MOTION, "push")
    return [n for n in names if not named(table, n).empty]


def _learned_best(table, yardsticks: list[str]) -> float | None:
    """The planning IoU to bold: the highest of the planners (not a reference row) whose paired difference from
    each yardstick (no push, random) has a 95% interval above 0; None when none has, or a yardstick is missing."""
    if len(yardsticks) < 2:
        return None
    bases = [unit_values(named(table, y).iloc[0][SEQ], "planning_iou") for y in yardsticks]
    planners = [r for _, r in table.iterrows() if not is_reference_row(r) and not is_oracle_row(r)]
    winners = [r["planning_iou"] for r in planners if all(
        (d := paired_difference(unit_values(r[SEQ], "planning_iou"), b)).excludes_zero and d.mean > 0 for b in bases)]
    return max(winners) if winners else None


def md_row(cells: list[str]) -> str:
    return "| " + " | ".join(cells) + " |"


def html_table(header: list[str], rows: list[list[Cell]], css: str) -> str:
    """A sortable table: rows of (text, sort value, classes) cells."""
    ths = "".join(f"<th onclick=\"sortTable(this)\">{html.escape(h)}</th>" for h in header)
    body = []
    for cells in rows:
        tds = []
        for text, value, classes in cells:
            attrs = (f' data-v="{html.escape(value)}"' if value is not None else "") + \
                (f' class="{classes}"' if classes else "")
            tds.append(f"<td{attrs}>{text}</td>")
        body.append("<tr>" + "".join(tds) + "</tr>")
    return f"<table class={css}><thead><tr>{ths}</tr></thead><tbody>{''.join(body)}</tbody></table>"


#: where a row may keep the links of its text cells ({column key: href}); the href is escaped where shown
LINKS = "_links"
#: the text columns every table has, in `load_rows`'s keys
TEXT_KEYS = ("method", "grid", "label", "toolkit", "date", "checksum")


@dataclass(frozen=True)
class RenderedTable:
    """A table rendered both ways: its header, its markdown lines (header, rule, one line per row), its HTML rows
    (`Cell`s) and whether its rows were compared with the reference rows (a best marked where they were)."""

    header: list[str]
    markdown: list[str]
    rows: list[list[Cell]]
    comparable: bool

    def html(self, css: str = "board") -> str:
        """The sortable HTML table (class `css`)."""
        return html_table(self.header, self.rows, css)


def render_table(rows: Any, track: str, columns: Sequence[str], published: bool = False,
                 lead: Sequence[tuple[str, str]] = ()) -> RenderedTable:
    """Render `rows` (a sequence of row mappings, or `board`'s DataFrame of them) of a `track` ("3D", "2D",
    "planning") table with metric `columns`, in this order: the `lead` columns ((title, row key): text, e.g. the
    challenge's rank and team), method, model grid, the metrics (value +- the 95% interval's half-width over the
    row's per-unit values; bold: the best non-oracle value where the table holds its no-motion row, or in planning a
    planner beating no push and random; a mark where worse than no motion; rows with a `ROLE` are marked among
    the rows of the same role only), a planning table's paired differences
    from no push and random, note, toolkit, date, split checksum. `published`: numbers reported in the paper (as
    printed, never compared)."""
    table = rows if hasattr(rows, "iterrows") else _frame(rows, columns, [key for _, key in lead])
    cols, paper = list(columns), published
    yardsticks = _yardsticks(table, track) if not paper else []
    inline = yardsticks if track == "planning" else []  # a planning table's paired differences: its own columns
    header = [*[title for title, _ in lead], "method", "model grid", *[COLUMN_TITLES[c] for c in cols],
              *[f"vs {y.replace(' (planning)', '')} (paired, \u00b1 SE)" for y in inline], "note", "toolkit",
              "date", "split checksum"]
    comparable, _ = _marks(table, track, cols, paper)
    groups = {role: (*_marks(peers, track, cols, paper), _no_motion_values(peers, cols))
              for role, peers in _groups(table)}
    md = [md_row(header), "|" + "---|" * len(header)]
    html_rows = []
    for _, r in table.iterrows():
        links = r.get(LINKS) if LINKS in r else None
        links = links if isinstance(links, dict) else {}
        _, best, no_motion = groups[r[ROLE] if ROLE in r else ""]
        cells, tds = [], []
        for c in cols:
            text = _cell(r, c) if not paper else _fmt(r[c], c, published=True)
            top = best[c] is not None and r[c] == best[c] and not is_oracle_row(r) and not (
                track == "planning" and is_reference_row(r))
            worse = _worse_than_no_motion(no_motion[c], c, r)
            cells.append((f"**{text}**" if top else text) + (f" {_WORSE_MARK}" if worse else ""))
            classes = " ".join(k for k, on in (("best", top), ("worse", worse)) if on)
            value = "" if r[c] != r[c] else repr(float(r[c]))  # NaN: no value to sort on
            tds.append((html.escape(text) + (f" {_WORSE_MARK}" if worse else ""), value, classes))
        for y in inline:
            base = named(table, y).iloc[0]
            d = paired_difference(unit_values(r[SEQ], "planning_iou"), unit_values(base[SEQ], "planning_iou"))
            text = "-" if is_named(r, y) else _difference(d, "planning_iou")
            cells.append(text)
            tds.append((html.escape(text), "" if text == "-" else repr(d.mean), ""))
        label = r["label"]
        if not paper and is_reference_row(r) and "reference" not in str(label):
            label = "reference" + (f"; {label}" if label else "")
        leads = [str(r[key]) for _, key in lead]
        md.append(md_row([*[markdown_cell(t) for t in leads], markdown_cell(r["method"]), markdown_cell(r["grid"]),
                           *cells, markdown_cell(label), markdown_cell(r["toolkit"]), markdown_cell(r["date"]),
                           markdown_cell(r["checksum"])]))
        html_rows.append([*[(_linked(t, links.get(key)), None, "") for t, (_, key) in zip(leads, lead)],
                          (_linked(str(r["method"]), links.get("method")), None, ""),
                          (html.escape(str(r["grid"])), None, ""),
                          *tds, (html.escape(str(label)), None, ""), (html.escape(str(r["toolkit"])), None, ""),
                          (html.escape(str(r["date"])), None, ""),
                          (f"<code>{html.escape(str(r['checksum']))}</code>", None, "")])
    return RenderedTable(header, md, html_rows, comparable)


def _groups(table) -> list[tuple[str, Any]]:
    """The table's rows in the groups marked apart: by role where rows say theirs (a challenge's submissions, scored on
    its hidden set, are never compared with reference rows scored on a public split), else all together."""
    if ROLE not in table:
        return [("", table)]
    return [(role, table[table[ROLE] == role]) for role in dict.fromkeys(table[ROLE])]


def _marks(table, track: str, cols: list[str], paper: bool) -> tuple[bool, dict[str, float | None]]:
    """(whether the rows can be compared with their reference rows, the value to bold per column or None): the
    best non-oracle value where the rows hold the no-motion row; in planning, a planner beating no push and random."""
    if track == "planning":
        yardsticks = _yardsticks(table, track) if not paper else []
        return (not paper and len(yardsticks) == 2,
                {c: _learned_best(table, yardsticks) if not paper else _best(table, c) for c in cols})
    comparable = not paper and not named(table, NO_MOTION).empty
    return comparable, {c: _best(table, c) if comparable or paper else None for c in cols}


def _linked(text: str, href: str | None) -> str:
    """`text` escaped, inside a link to `href` (escaped) when there is one."""
    return f'<a href="{html.escape(href)}">{html.escape(text)}</a>' if href else html.escape(text)


def _number(value: Any) -> float:
    return float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else math.nan


def _frame(rows: Sequence[Mapping[str, Any]], columns: Sequence[str], lead_keys: Sequence[str]) -> Any:
    """A DataFrame of row mappings: every text column a string ("" where missing), every metric a float (NaN where
    missing), the per-unit values and links a dict."""
    import pandas as pd

    rows = list(rows)
    data: dict[str, list] = {k: ["" if r.get(k) is None else str(r.get(k)) for r in rows]
                             for k in dict.fromkeys((*TEXT_KEYS, *lead_keys))}
    data.update({c: [_number(r.get(c)) for r in rows] for c in columns})
    data[SEQ] = [dict(r.get(SEQ) or {}) for r in rows]
    data[LINKS] = [dict(r.get(LINKS) or {}) for r in rows]
    data[ROLE] = ["" if r.get(ROLE) is None else str(r.get(ROLE)) for r in rows]
    if any(r.get(REFERENCE) is not None for r in rows):  # rows that say which reference row they are (else: None)
        data[REFERENCE] = [r.get(REFERENCE) for r in rows]
    return pd.DataFrame(data)

"""The leaderboard: results entries (one JSON per entry) and the tables built from them.

leaderboard/entries/*.json are results files written by `dsr-bench evaluate` (plus an optional
"label"); leaderboard/paper.json holds the paper's published numbers, always shown apart and
marked "reported in the paper". A 2D-only entry (results holding motion_2d alone) joins the 2D track's
table only. leaderboard/planning/*.json are results files of `dsr-bench plan` (complete runs on a pinned
task set), shown in the planning IoU column. `build` writes leaderboard/README.md (a table per split and track,
best per column in bold), a static, sortable leaderboard/index.html and, for each table of reproduced rows
whose entries hold per-step values, leaderboard/plots/<split>-3d.png (-2d.png for the 2D track; an earlier
version of a split: <split>-<checksum>-3d.png) comparing the rows step by step, shown under the table.
"""

from __future__ import annotations

import html
import json
import re
from pathlib import Path

from dsr_bench.atomic import write_text
from dsr_bench.constants import GRID_SHAPE, IMAGE_SHAPE
from dsr_bench.errors import UserError

LOWER_IS_BETTER = {"motion_visible", "motion_full", "motion_2d"}
TRACKS = {"3D": ("motion_visible", "motion_full", "iou_unordered", "iou_ordered"), "2D": ("motion_2d",)}
COLUMN_TITLES = {"motion_visible": "flow MSE visible (cm²)", "motion_full": "flow MSE full (cm²)",
                 "iou_unordered": "IoU unordered", "iou_ordered": "IoU ordered", "motion_2d": "2D flow MSE (cm²)",
                 "planning_iou": "planning IoU"}


def _number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def is_2d_only(metrics: dict) -> bool:
    """Whether a results file's metrics are a 2D-only submission's: none of the 3D track's, motion_2d present."""
    from dsr_bench.scoring.evaluate import HEADLINE

    return "motion_2d" in metrics and not any(k in metrics for k in HEADLINE)


def check_entry(results: dict) -> list[str]:
    """Problems that keep a results file off the leaderboard (empty list: it may join)."""
    from dsr_bench.scoring.evaluate import HEADLINE, RESULTS_FORMAT
    from dsr_bench.dataset.splits import SPLITS

    problems = []
    if results.get("format") != RESULTS_FORMAT:
        return [f"not a dsr-bench results file (format {results.get('format')!r}); produce it with `dsr-bench evaluate`"]
    metrics = results.get("metrics") if isinstance(results.get("metrics"), dict) else {}
    if is_2d_only(metrics):  # a 2D-only submission: the 2D track's metric
        if not _number(metrics.get("motion_2d")):
            problems.append("metrics missing: motion_2d (a 2D-only submission's metric)")
    else:
        missing = [k for k in HEADLINE if not _number(metrics.get(k))]
        if missing:
            problems.append(f"metrics missing: {', '.join(missing)}")
    if results.get("coverage", {}).get("partial"):
        problems.append("partial evaluation (--allow-partial): the leaderboard needs every sequence of the split")
    split = results.get("split")
    if split not in SPLITS:
        problems.append(f"split {split!r} is not one of the benchmark's named splits")
    else:
        expected = SPLITS[split].expected_digest
        if expected is None:
            problems.append(f"split {split!r} has no pinned checksum in this toolkit version; it cannot be ranked")
        elif results.get("split_checksum") != expected:
            problems.append(f"split checksum {str(results.get('split_checksum'))[:12]}... differs from the toolkit's "
                            f"{expected[:12]}... for {split}: regenerate the split with `dsr-bench generate --split {split}`")
    return problems


def add_entry(results_path: str | Path, root: str | Path = "leaderboard", label: str | None = None) -> Path:
    """Validate a results file and copy it into the leaderboard's entries."""
    path = Path(results_path)
    try:
        results = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise UserError(f"{path}: unreadable results file ({exc})") from None
    if isinstance(results, dict) and results.get("format") == PLAN_RESULTS_FORMAT:
        return _add_plan_entry(path, results, Path(root))
    problems = check_entry(results)
    if problems:
        raise UserError(f"{path} cannot join the leaderboard: " + "; ".join(problems))
    if label:
        results["label"] = label
    slug = re.sub(r"[^a-z0-9]+", "-", f"{results['method']}-{results['split']}".lower()).strip("-")
    entries = Path(root) / "entries"
    entries.mkdir(parents=True, exist_ok=True)
    target = entries / f"{slug}.json"
    write_text(target, json.dumps(results, indent=1, sort_keys=True) + "\n")
    return target


def _kind(results: dict) -> str:
    """The table an entry belongs to, beside its split: the split's current pin, or an earlier version of it."""
    from dsr_bench.dataset.splits import SPLITS

    expected = SPLITS[results["split"]].expected_digest if results["split"] in SPLITS else None
    checksum = results.get("split_checksum", "")
    # an entry scored on an earlier pin of its split stays visible, in its own table, unranked against the rest
    return "reproduced" if checksum == expected else f"reproduced on an earlier version of the split, {checksum[:12]}"


#: Results of `dsr-bench plan` (the planning track), kept in leaderboard/planning/ and shown in the planning IoU column.
PLAN_RESULTS_FORMAT = "dsr-bench-plan-results"


def _add_plan_entry(path: Path, results: dict, root: Path) -> Path:
    """Copy a planning results file into leaderboard/planning/: only a complete run on a pinned task set."""
    metrics = results.get("metrics") if isinstance(results.get("metrics"), dict) else {}
    coverage = results.get("coverage") if isinstance(results.get("coverage"), dict) else {}
    iou = metrics.get("iou")
    problems = []
    if not isinstance(iou, (int, float)) or isinstance(iou, bool) or not 0 <= iou <= 1:
        problems.append(f"metrics.iou must be a number in [0, 1], got {iou!r}")
    if results.get("pinned") is not True:
        problems.append("its task set is not this toolkit's pinned one; plan on a pinned task set "
                        "(`dsr-bench generate-plan-tasks --tasks plan-novel-test`)")
    if coverage.get("partial") is not False:
        problems.append("it covers only part of the task set; run `dsr-bench plan` on every task")
    if not isinstance(results.get("method"), str) or not isinstance(results.get("task_set"), str):
        problems.append("method and task_set must be strings")
    if problems:
        raise UserError(f"{path} cannot join the leaderboard: " + "; ".join(problems))
    slug = re.sub(r"[^a-z0-9]+", "-", f"{results['method']}-{results['task_set']}".lower()).strip("-")
    target = root / "planning" / f"{slug}.json"
    target.parent.mkdir(parents=True, exist_ok=True)
    write_text(target, json.dumps(results, indent=1, sort_keys=True) + "\n")
    return target


def load_entries(root: str | Path = "leaderboard") -> list[dict]:
    """Every entry's results (entries/*.json, sorted by file name), each with its table's "kind" added."""
    entries = []
    for path in sorted((Path(root) / "entries").glob("*.json")):
        r = json.loads(path.read_text())
        entries.append({**r, "kind": _kind(r)})
    return entries


def load_rows(root: str | Path = "leaderboard") -> list[dict]:
    """Flat rows (method, split, kind, metrics, date, checksum, label) of every entry and paper row."""
    root = Path(root)
    rows = []
    for r in load_entries(root):
        kind = r["kind"]
        # the model's grid, or the image an image-space model works on (parameters "image"; a 2D-only entry
        # that names neither: the front camera's)
        params = (r.get("meta") or {}).get("parameters") or {}
        default = IMAGE_SHAPE if is_2d_only(r.get("metrics") or {}) else GRID_SHAPE
        grid = params.get("grid") or params.get("image") or list(default)
        rows.append({"method": r["method"], "split": r["split"], "kind": kind, "label": r.get("label", ""),
                     "grid": "x".join(str(int(g)) for g in grid),
                     "date": r.get("date", "")[:10], "checksum": r.get("split_checksum", "")[:12],
                     **{k: v for k, v in r["metrics"].items()}})
    from dsr_bench.planning.scoring import leaderboard_rows

    rows += leaderboard_rows(sorted((root / "planning").glob("*.json")), include_paper=False)  # paper.json has them
    paper = root / "paper.json"
    if paper.exists():
        for r in json.loads(paper.read_text())["rows"]:
            rows.append({"method": r["method"], "split": r["split"], "kind": "reported in the paper",
                         "grid": "x".join(map(str, GRID_SHAPE)),
                         "label": r.get("source", ""), "date": "2020", "checksum": "", **r["metrics"]})
    return rows


def _tables(rows: list[dict]):
    import pandas as pd

    frame = pd.DataFrame(rows)
    for (split, kind), group in frame.groupby(["split", "kind"], sort=True):
        if "planning_iou" in group and group["planning_iou"].notna().all():  # a planning task set's own table
            yield split, kind, "planning", group[["method", "grid", "planning_iou", "label", "date", "checksum"]
                                                 ].reset_index(drop=True), ["planning_iou"]
            continue
        for track, columns in TRACKS.items():
            cols = [c for c in columns + (("planning_iou",) if track == "3D" else ()) if c in group]
            sub = group.dropna(subset=[c for c in cols if c in group], how="all")
            if sub.empty or not cols:
                continue
            yield split, kind, track, sub[["method", "grid", *cols, "label", "date", "checksum"]].reset_index(drop=True), cols


_WORSE_MARK = "\u25bc"

#: Rows that bound the benchmark from above: never "best" (ground truth as predictions, or a model
#: warped with the ground-truth flow).
def is_oracle(method: str) -> bool:
    """Whether a row is an oracle: its method is `oracle` or says "oracle" (e.g. "GTWarp (oracle warp)"), or it is
    GTWarp (`gtwarp`, `gtwarp-cpu`: its history is warped by the ground-truth flow)."""
    name = str(method).lower()
    return "oracle" in name or name.startswith("gtwarp")


#: The reference row every trained row must beat: predicting no motion.
NO_MOTION = "static"


def _best(table, column):
    """The best non-oracle value of a column, or None (no bold) when the table has no no-motion reference row
    of reproduced results: a best that cannot be compared with predicting no motion is not marked."""
    values = table[[not is_oracle(m) for m in table["method"]]][column].dropna()
    if values.empty:
        return None
    return values.min() if column in LOWER_IS_BETTER else values.max()


def _worse_than_no_motion(table, column, row) -> bool:
    """Whether a trained row's value is worse than the no-motion reference row's in the same table."""
    ref = table[table["method"] == NO_MOTION][column].dropna()
    if ref.empty or row["method"] == NO_MOTION or is_oracle(row["method"]) or row[column] != row[column]:
        return False
    return row[column] > ref.iloc[0] if column in LOWER_IS_BETTER else row[column] < ref.iloc[0]


def _fmt(value, column) -> str:
    if value is None or value != value:
        return "-"
    return f"{value:.3f}" if column.startswith(("iou", "planning")) else f"{value:.4g}"


def build(root: str | Path = "leaderboard") -> tuple[Path, Path]:
    """Write README.md and index.html of the leaderboard from its entries and paper rows."""
    from dsr_bench.dataset.splits import SPLITS

    root = Path(root)
    rows = load_rows(root)
    entries = load_entries(root)
    plotted: set[Path] = set()
    md = ["# dsr-bench leaderboard", "",
          "Built by `dsr-bench leaderboard build` from `entries/` (results of `dsr-bench evaluate`) and",
          "`paper.json` (numbers reported in the paper, never mixed with reproduced rows). In each table of reproduced",
          "results the reference rows (oracle, static = predicting no motion, push = every object voxel moved along",
          "the push) sit beside the trained rows of the same version of the split. Bold: the best value that is not an",
          "oracle's, marked only where the table holds the no-motion row to compare with. " + _WORSE_MARK + ": worse",
          "than predicting no motion.", ""]
    body = []
    for split, kind, track, table, cols in _tables(rows):
        md += [f"## {split}: {track} track ({kind})", ""]
        if split in SPLITS:
            md += [f"{SPLITS[split].description}.", ""]
        header = ["method", "model grid", *[COLUMN_TITLES[c] for c in cols], "note", "date", "split checksum"]
        # a planning table compares planners with each other (random is its yardstick), not with a no-motion row
        comparable = kind != "reported in the paper" and (track == "planning" or (table["method"] == NO_MOTION).any())
        best = {c: _best(table, c) if comparable or kind == "reported in the paper" else None for c in cols}
        if kind != "reported in the paper" and not comparable:
            md += ["No no-motion (static) row was scored on this version of the split: these rows cannot be compared "
                   "with predicting no motion, and none is marked best.", ""]
        md += ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
        html_rows = []
        for _, r in table.iterrows():
            cells, tds = [], []
            for c in cols:
                text, top = _fmt(r[c], c), best[c] is not None and r[c] == best[c] and not is_oracle(r["method"])
                worse = _worse_than_no_motion(table, c, r)
                cells.append((f"**{text}**" if top else text) + (f" {_WORSE_MARK}" if worse else ""))
                classes = " ".join(k for k, on in (("best", top), ("worse", worse)) if on)
                tds.append(f'<td data-v="{"" if r[c] != r[c] else r[c]}"{f" class={chr(34)}{classes}{chr(34)}" if classes else ""}>'
                           f"{html.escape(_fmt(r[c], c))}{f' {_WORSE_MARK}' if worse else ''}</td>")
            md.append("| " + " | ".join([str(r["method"]), str(r["grid"]), *cells, str(r["label"]), str(r["date"]), str(r["checksum"])]) + " |")
            html_rows.append(f"<tr><td>{html.escape(str(r['method']))}</td><td>{html.escape(str(r['grid']))}</td>{''.join(tds)}<td>{html.escape(str(r['label']))}"
                             f"</td><td>{html.escape(str(r['date']))}</td><td><code>{html.escape(str(r['checksum']))}</code>"
                             "</td></tr>")
        md.append("")
        plot = _table_plot(root, entries, split, kind, track)
        if plot is not None:
            plotted.add(plot)
            rel = plot.relative_to(root).as_posix()
            md += ["Per step (one line per row; dashed: reference rows):", "",
                   f"![{split}, {track} track: per-step curves]({rel})", ""]
        ths = "".join(f"<th onclick=\"sortTable(this)\">{html.escape(h)}</th>" for h in header)
        note = ("" if comparable or kind == "reported in the paper" else
                "<p class=note>No no-motion (static) row on this version of the split: not comparable, none marked best.</p>")
        about = f"<p>{html.escape(SPLITS[split].description)}.</p>" if split in SPLITS else ""
        figure = ("" if plot is None else
                  f'<figure><a href="{html.escape(rel)}"><img src="{html.escape(rel)}" alt="{html.escape(split)}, '
                  f'{track} track: per-step curves" width="860"></a><figcaption>Per step, one line per row '
                  "(dashed: reference rows).</figcaption></figure>")
        body.append(f"<h2>{html.escape(split)}: {track} track ({html.escape(kind)})</h2>\n{about}{note}"
                    f"<table class=board><thead><tr>{ths}</tr></thead><tbody>{''.join(html_rows)}</tbody></table>"
                    f"{figure}")
    if not rows:
        md.append("No entries yet.")
    page = _PAGE.replace("{body}", "\n".join(body) or "<p>No entries yet.</p>")
    write_text(root / "README.md", "\n".join(md) + "\n")
    write_text(root / "index.html", page)
    for stale in sorted((root / PLOTS_DIR).glob("*-[23]d.png")):  # a plot of a table that no longer exists
        if stale not in plotted:
            stale.unlink(missing_ok=True)
    return root / "README.md", root / "index.html"


#: Where `build` writes the per-step plots, under the leaderboard's root.
PLOTS_DIR = "plots"


def plot_name(split: str, kind: str, track: str) -> str:
    """The file name of a table's per-step plot: <split>-3d.png, or <split>-<checksum>-3d.png for an earlier
    version of the split."""
    version = "" if kind == "reproduced" else "-" + kind.rsplit(", ", 1)[-1]
    return re.sub(r"[^A-Za-z0-9._-]+", "-", f"{split}{version}") + f"-{track.lower()}.png"


def _table_plot(root: Path, entries: list[dict], split: str, kind: str, track: str) -> Path | None:
    """Write the per-step plot of one table of reproduced rows (None: paper rows, or no entry has per-step
    values for the track)."""
    from dsr_bench.scoring.plots import MISSING_MATPLOTLIB, leaderboard_series, matplotlib_missing, \
        write_leaderboard_plot

    if not kind.startswith("reproduced") or track == "planning":  # plans have no per-step prediction values
        return None
    panels = leaderboard_series([e for e in entries if e["split"] == split and e["kind"] == kind], track)
    if not panels:
        return None
    if matplotlib_missing():
        raise UserError(f"cannot draw {root / PLOTS_DIR}: {MISSING_MATPLOTLIB}")
    title = f"{split}: {track} track" + ("" if kind == "reproduced" else f" ({kind})")
    return write_leaderboard_plot(panels, title, root / PLOTS_DIR / plot_name(split, kind, track))


_PAGE = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>dsr-bench leaderboard</title>
<style>
body{font-family:system-ui,sans-serif;margin:2em;max-width:1100px}
table{border-collapse:collapse;margin-bottom:2em}th,td{border:1px solid #ccc;padding:4px 8px;text-align:right}
td:first-child,th:first-child{text-align:left}th{cursor:pointer;background:#f4f4f4}.best{font-weight:bold}
.worse{color:#a00}.note{color:#555}figure{margin:0 0 2em 0}img{max-width:100%}
</style></head><body>
<h1>dsr-bench leaderboard</h1>
<p>Reproduced results (<code>dsr-bench evaluate</code>) and numbers reported in the paper, in separate tables.
Reference rows (oracle, static = predicting no motion, push) sit beside the trained rows of the same version of a split.
Click a column to sort. Bold: the best value that is not an oracle's. &#9660; (red): worse than predicting no motion.</p>
{body}
<script>
function sortTable(th){
  const table=th.closest('table'), i=[...th.parentNode.children].indexOf(th), body=table.tBodies[0];
  const asc=th.dataset.asc!=='1'; th.dataset.asc=asc?'1':'0';
  const key=r=>{const c=r.children[i]; const v=c.dataset.v; return v!==undefined&&v!==''?parseFloat(v):c.textContent;};
  [...body.rows].sort((a,b)=>{const x=key(a),y=key(b); return (x>y?1:x<y?-1:0)*(asc?1:-1);}).forEach(r=>body.appendChild(r));
}
</script></body></html>
"""

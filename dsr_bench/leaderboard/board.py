"""The leaderboard: results entries (one JSON per entry) and the tables built from them.

leaderboard/entries/*.json are results of `dsr-bench evaluate` as `add` recomputed them from the predictions
(plus an optional "label"), never a submitted file's numbers; leaderboard/planning/*.json likewise results of
`dsr-bench plan` recomputed from the plan files (complete runs on a pinned task set), shown in the planning IoU
column. `dsr_bench.leaderboard.entries` validates both before `add` writes and when `build` reads (a file that fails
is skipped with one warning line). leaderboard/paper.json holds the paper's published numbers, always shown apart
and marked "reported in the paper". A 2D-only entry (results holding motion_2d alone) joins the 2D track's table
only. `build` writes leaderboard/README.md (a table per split and track, best per column in bold; every text
cell escaped), a static, sortable leaderboard/index.html and, for each table of reproduced rows whose entries
hold per-step values, leaderboard/plots/<split>-3d.png (-2d.png for the 2D track; an earlier version of a split:
<split>-<checksum>-3d.png) comparing the rows step by step, shown under the table.
"""

from __future__ import annotations

import html
import json
import re
import sys
from collections.abc import Callable
from pathlib import Path

from dsr_bench.atomic import write_text
from dsr_bench.constants import GRID_SHAPE, IMAGE_SHAPE
from dsr_bench.errors import UserError
from dsr_bench.models.predictors import REFERENCE_MODELS
from dsr_bench.leaderboard.entries import (PLAN_RESULTS_FORMAT, RESULTS_FORMAT, check_entry, entry_identity,
                                       entry_name, first_difference, is_2d_only, markdown_cell, show)
from dsr_bench.scoring.metrics import METRICS, TRACKS as METRIC_TRACKS, metric_keys

#: each track's columns: its headline metrics (`dsr_bench.scoring.metrics.METRICS`), titled and ranked as they say
TRACKS = {track: metric_keys((track,), ("headline",)) for track in METRIC_TRACKS}
LOWER_IS_BETTER = {m.key for m in METRICS if m.role == "headline" and m.lower_is_better}
COLUMN_TITLES = {**{m.key: m.column for m in METRICS if m.column}, "planning_iou": "planning IoU"}


def add_entry(results_path: str | Path, root: str | Path = "leaderboard", label: str | None = None,
              predictions: str | Path | None = None, data: str | Path | None = None, plans: str | Path | None = None,
              tasks: str | Path | None = None, workers: int = 0) -> tuple[Path, bool]:
    """Recompute a results file from its predictions (`evaluate`) or plans (`planning.verify.recompute_results`),
    refuse it (UserError, one line, nothing written) unless the recomputed results are pinned, complete, a valid
    entry and equal to the file in every field but date, label and toolkit_version, and write the recomputed
    results (plus `label`). Returns (the entry's file, whether it replaced the entry of the same method, split and
    predictions)."""
    path, root = Path(results_path), Path(root)
    try:
        submitted = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise UserError(f"{path}: unreadable results file ({type(exc).__name__}); give the results JSON of "
                        "`dsr-bench evaluate --out` or `dsr-bench plan`") from None
    kind = submitted.get("format") if isinstance(submitted, dict) else None
    if kind == PLAN_RESULTS_FORMAT:
        recomputed = _recompute_plans(path, plans, tasks, root)
        source, folder = "plans", "planning"
    elif kind == RESULTS_FORMAT:
        recomputed = _recompute_predictions(path, submitted, predictions, data, root, workers)
        source, folder = "predictions", "entries"
    else:
        raise UserError(f"{path} is not a dsr-bench results file (format {show(kind)}); produce it with "
                        "`dsr-bench evaluate --out` or `dsr-bench plan`")
    difference = first_difference(submitted, recomputed, source)
    if difference:
        again = "`dsr-bench plan`" if source == "plans" else "`dsr-bench evaluate`"
        raise UserError(f"{path}: {difference}; re-run {again} and add the results it writes")
    entry = {**recomputed, **({"label": label} if label else {})}
    # the file itself must be well formed too (its date, label and toolkit_version were not compared)
    problems = check_entry(entry) or check_entry(submitted)
    if problems:
        raise UserError(f"{path} cannot join the leaderboard: {_first(problems)}")
    target, replaced = _entry_path(root / folder, entry)
    write_text(target, json.dumps(entry, indent=1, sort_keys=True) + "\n")
    return target, replaced


def _first(problems: list[str]) -> str:
    return problems[0] + (f" (and {len(problems) - 1} more)" if len(problems) > 1 else "")


def _recompute_predictions(path: Path, submitted: dict, predictions, data, root: Path, workers: int) -> dict:
    """The results of `evaluate` on the predictions, on the file's split: pinned and complete, else UserError."""
    from dsr_bench.atomic import check_writable
    from dsr_bench.scoring.evaluate import evaluate
    from dsr_bench.scoring.predictions import infer_source

    if predictions is None:
        raise UserError(f"{path}: the leaderboard recomputes every score from the predictions and never reads one "
                        "from a results file; give --predictions PRED_DIR (the directory `dsr-bench evaluate` scored)")
    split = submitted.get("split")
    if not isinstance(split, str):
        raise UserError(f"{path}: split is {show(split)}, not a split's name; produce the results with "
                        "`dsr-bench evaluate`")
    check_writable(root / "entries", "--root")
    predictions = Path(predictions)
    if not predictions.is_dir():
        raise UserError(f"--predictions {predictions}: not a directory; give the predictions `dsr-bench evaluate` "
                        "scored")
    data, _, _ = infer_source(predictions, Path(data) if data is not None else None, split)  # split as given
    evaluation = evaluate(predictions, data, split, workers=workers)
    if evaluation.results is None:
        where, problem = evaluation.problems[0] if evaluation.problems else ("", "nothing scored")
        raise UserError(f"{predictions}: {len(evaluation.problems)} problems (first: {where}: {problem}); run "
                        f"`dsr-bench evaluate {predictions}` to see them all")
    results = json.loads(json.dumps(evaluation.results))  # as a results file holds it
    if results.get("pinned") is not True:
        why = evaluation.warnings[0] if evaluation.warnings else f"split {split!r} is not pinned in this toolkit"
        raise UserError(f"{path} cannot join the leaderboard: recomputed on {data}, its results are not pinned: {why}")
    if results["coverage"]["partial"]:
        raise UserError(f"{path} cannot join the leaderboard: the predictions cover only part of {split}")
    reference = reference_model(results["method"])
    if reference is not None:
        check_reference_predictions(path, predictions, data, split, reference)
    return results


#: the reference rows' methods, made by `dsr-bench predict --model NAME`: a table's yardsticks (static: the no-motion
#: row every trained row is compared with), so a submission may carry such a name only with those very predictions
REFERENCE_ROWS = REFERENCE_MODELS


def reference_model(method: str) -> str | None:
    """The reference model a method's name claims to be (case, spaces and punctuation aside), or None."""
    name = re.sub(r"[^a-z0-9]", "", str(method).lower())
    return name if name in REFERENCE_ROWS else None


def check_reference_predictions(path: Path, predictions: Path, data: Path, split: str, model: str) -> None:
    """UserError unless every prediction file holds exactly the arrays `dsr-bench predict --model MODEL` writes for
    it (predicted again here): a reference row's name is the toolkit's to give, never a submitter's."""
    import tempfile

    import h5py
    import numpy as np

    from dsr_bench.dataset.manifest import read_split
    from dsr_bench.models.predictors import load_predictor, predict_split

    _, names = read_split(data, split)
    with tempfile.TemporaryDirectory(prefix="dsr-bench-reference-") as tmp:
        predict_split(load_predictor(model), data, names, tmp)
        for name in names:
            with h5py.File(Path(tmp) / f"{name}.h5", "r") as want, h5py.File(predictions / f"{name}.h5", "r") as got:
                same = set(want) == set(got) and want.attrs.get("num_slots") == got.attrs.get("num_slots") and all(
                    want[k].dtype == got[k].dtype and np.array_equal(want[k][()], got[k][()]) for k in want)
            if not same:
                raise UserError(f"{path}: its method is named like the reference row {model!r}, but "
                                f"{predictions / (name + '.h5')} is not what `dsr-bench predict --model {model}` "
                                "writes; give your method another name (meta.json's name)")


def _recompute_plans(path: Path, plans, tasks, root: Path) -> dict:
    """The planning results recomputed from the plan files and the verified tasks: pinned and complete, else
    UserError."""
    from dsr_bench.atomic import check_writable
    from dsr_bench.planning.verify import recompute_results

    if plans is None:
        raise UserError(f"{path}: the leaderboard recomputes every planning score from the plan files and never reads "
                        "one from a results file; give --plans PLANS_DIR (the --out directory of `dsr-bench plan`)")
    check_writable(root / "planning", "--root")
    results = json.loads(json.dumps(recompute_results(Path(plans), tasks)))
    problems = check_entry(results)
    if problems:
        raise UserError(f"{path} cannot join the leaderboard: recomputed from {plans}, {_first(problems)}")
    return results


def _entry_path(folder: Path, entry: dict) -> tuple[Path, bool]:
    """Where an entry goes: the file already holding the same method, split and predictions (plans), replaced,
    or its own new file (`entries.entry_name`)."""
    identity = entry_identity(entry)
    for existing in sorted(folder.glob("*.json")):
        try:
            old = json.loads(existing.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError):
            continue
        if isinstance(old, dict) and entry_identity(old) == identity:
            return existing, True
    folder.mkdir(parents=True, exist_ok=True)
    return folder / entry_name(entry), False


def _read_valid(paths, kind: str, warn) -> list[tuple[Path, dict]]:
    """The files that are valid entries of their kind (results or planning results); one warning line for each
    that is not, naming the file and its (first) problem."""
    valid = []
    for path in paths:
        try:
            r = json.loads(path.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            warn(f"skipped {path}: unreadable ({type(exc).__name__})")
            continue
        problems = check_entry(r) if isinstance(r, dict) and r.get("format") == kind else \
            [f"not a {kind} file (format {show(r.get('format') if isinstance(r, dict) else r)})"]
        if problems:
            warn(f"skipped {path}: {_printable(_first(problems))}")
        else:
            valid.append((path, r))
    return valid


def _printable(text: str) -> str:
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


def _stderr(line: str) -> None:
    print(f"warning: {line}", file=sys.stderr)


def _kind(results: dict) -> str:
    """The table an entry belongs to, beside its split: the split's current pin, or an earlier version of it."""
    from dsr_bench.dataset.splits import SPLITS

    expected = SPLITS[results["split"]].expected_digest if results["split"] in SPLITS else None
    checksum = results.get("split_checksum", "")
    # an entry scored on an earlier pin of its split stays visible, in its own table, unranked against the rest
    return "reproduced" if checksum == expected else f"reproduced on an earlier version of the split, {checksum[:12]}"


def load_entries(root: str | Path = "leaderboard", warn: Callable[[str], None] | None = None) -> list[dict]:
    """Every valid entry's results (entries/*.json, sorted by file name), each with its table's "kind" added; an
    invalid file is skipped with one `warn` line (default: on stderr)."""
    paths = sorted((Path(root) / "entries").glob("*.json"))
    return [{**r, "kind": _kind(r)} for _, r in _read_valid(paths, RESULTS_FORMAT, warn or _stderr)]


def load_rows(root: str | Path = "leaderboard", warn: Callable[[str], None] | None = None,
              entries: list[dict] | None = None) -> list[dict]:
    """Flat rows (method, split, kind, metrics, date, checksum, label) of every valid entry (`entries`, default
    `load_entries`), valid planning entry and paper row."""
    root = Path(root)
    rows = []
    for r in load_entries(root, warn) if entries is None else entries:
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
    plans = _read_valid(sorted((root / "planning").glob("*.json")), PLAN_RESULTS_FORMAT, warn or _stderr)
    rows += planning_rows([path for path, _ in plans], include_paper=False)  # paper.json has them
    paper = root / "paper.json"
    if paper.exists():
        for r in json.loads(paper.read_text())["rows"]:
            rows.append({"method": r["method"], "split": r["split"], "kind": "reported in the paper",
                         "grid": "x".join(map(str, GRID_SHAPE)),
                         "label": r.get("source", ""), "date": "2020", "checksum": "", **r["metrics"]})
    return rows


#: Leaderboard rows of the paper (Sec. 4.3), planning IoU over its 100 simulated targets.
PLANNING_PAPER_ROWS = (("DSR-Net", 0.72), ("SE3-Net (planning)", 0.31), ("SE3Pose-Net (planning)", 0.32))


def planning_rows(results_files: list[str | Path], include_paper: bool = True) -> list[dict]:
    """Rows for the leaderboard's planning column, in `load_rows`'s shape (method, split, kind, label, grid, date,
    checksum, planning_iou): one per results file of `dsr-bench plan` (`dsr_bench.planning.results.build_results`;
    kind "reproduced" when its task set matches the pin), and the paper's three rows."""
    rows = []
    for path in results_files:
        r = json.loads(Path(path).read_text())
        # the planner's model grid where the results record it (a learned planner); "-" for oracle and random
        grid = "x".join(str(int(g)) for g in (r.get("planner") or {}).get("grid") or ()) or "-"
        kind = "reproduced" if r.get("pinned") else f"task set not pinned ({r.get('task_checksum', '')[:12]})"
        partial = r["coverage"]["partial"]
        rows.append({"method": f"{r['method']} (planning)", "split": r["task_set"], "kind": kind,
                     "label": f"{r['coverage']['scored']}/{r['coverage']['expected']} tasks"
                              + (" (partial)" if partial else ""),
                     "grid": grid, "date": r.get("date", "")[:10], "checksum": r.get("task_checksum", "")[:12],
                     "planning_iou": r["metrics"]["iou"]})
    if include_paper:
        rows += [{"method": m, "split": "ycb-test", "kind": "reported in the paper", "label": "Sec. 4.3",
                  "grid": "x".join(map(str, GRID_SHAPE)),
                  "date": "2020", "checksum": "", "planning_iou": v} for m, v in PLANNING_PAPER_ROWS]
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
            table = sub[["method", "grid", *cols, "label", "date", "checksum"]].reset_index(drop=True)
            yield split, kind, track, table, cols


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


def build(root: str | Path = "leaderboard", warn: Callable[[str], None] | None = None) -> tuple[Path, Path]:
    """Write README.md and index.html of the leaderboard from its valid entries and paper rows; each entry file
    that is not valid is skipped with one `warn` line naming it and its problem (default: on stderr)."""
    from dsr_bench.dataset.splits import SPLITS

    root = Path(root)
    entries = load_entries(root, warn)
    rows = load_rows(root, warn, entries)
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
                value = "" if r[c] != r[c] else r[c]  # NaN: no value to sort on
                tds.append(f'<td data-v="{value}"{f" class={chr(34)}{classes}{chr(34)}" if classes else ""}>'
                           f"{html.escape(_fmt(r[c], c))}{f' {_WORSE_MARK}' if worse else ''}</td>")
            md.append("| " + " | ".join([markdown_cell(r["method"]), markdown_cell(r["grid"]), *cells,
                                         markdown_cell(r["label"]), markdown_cell(r["date"]),
                                         markdown_cell(r["checksum"])]) + " |")
            html_rows.append(f"<tr><td>{html.escape(str(r['method']))}</td><td>{html.escape(str(r['grid']))}</td>"
                             f"{''.join(tds)}<td>{html.escape(str(r['label']))}"
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
                "<p class=note>No no-motion (static) row on this version of the split: not comparable, none marked "
                "best.</p>")
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
Click a column to sort. Bold: the best value that is not an oracle's. &#9660; (red): worse than predicting no \
motion.</p>
{body}
<script>
function sortTable(th){
  const table=th.closest('table'), i=[...th.parentNode.children].indexOf(th), body=table.tBodies[0];
  const asc=th.dataset.asc!=='1'; th.dataset.asc=asc?'1':'0';
  const key=r=>{const c=r.children[i]; const v=c.dataset.v; return v!==undefined&&v!==''?parseFloat(v):c.textContent;};
  [...body.rows].sort((a,b)=>{const x=key(a),y=key(b); return (x>y?1:x<y?-1:0)*(asc?1:-1);})\
.forEach(r=>body.appendChild(r));
}
</script></body></html>
"""

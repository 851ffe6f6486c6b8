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
from dsr_bench.leaderboard.table import (COLUMN_TITLES, LOWER_IS_BETTER, NO_MOTION, NO_PUSH, SEQ,  # noqa: F401
                                         SORT_SCRIPT, TRACKS, _WORSE_MARK, _difference, _yardsticks, html_table,
                                         is_oracle, md_row, render_table)
from dsr_bench.scoring.plots import FIGURE_WIDTH_PX, is_reference_method
from dsr_bench.scoring.spread import paired_difference, unit_values


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
                     "grid": "x".join(str(int(g)) for g in grid), "toolkit": str(r.get("toolkit_version", "")),
                     "date": r.get("date", "")[:10], "checksum": r.get("split_checksum", "")[:12],
                     SEQ: r.get("per_sequence") or {}, **{k: v for k, v in r["metrics"].items()}})
    plans = _read_valid(sorted((root / "planning").glob("*.json")), PLAN_RESULTS_FORMAT, warn or _stderr)
    rows += planning_rows([path for path, _ in plans], include_paper=False)  # paper.json has them
    paper = root / "paper.json"
    if paper.exists():
        for r in json.loads(paper.read_text())["rows"]:
            # an image-space model of the paper (2D flow alone) has no voxel grid, and the paper gives its image
            # size nowhere we quote: "-", never the 3D models' grid
            grid = "-" if set(r["metrics"]) == {"motion_2d"} else "x".join(map(str, GRID_SHAPE))
            rows.append({"method": r["method"], "split": r["split"], "kind": "reported in the paper", "grid": grid,
                         "toolkit": "", "label": r.get("source", ""), "date": "2020", "checksum": "", SEQ: {},
                         **r["metrics"]})
    return rows


#: Leaderboard rows of the paper (Sec. 4.3), planning IoU over its 100 simulated targets.
PLANNING_PAPER_ROWS = (("DSR-Net", 0.72), ("SE3-Net (planning)", 0.31), ("SE3Pose-Net (planning)", 0.32))


def planning_rows(results_files: list[str | Path], include_paper: bool = True) -> list[dict]:
    """Rows for the leaderboard's planning tables, in `load_rows`'s shape (method, split, kind, label, grid,
    toolkit, date, checksum, planning_iou, and the per-task IoUs under `SEQ`): one per results file of `dsr-bench
    plan` (`dsr_bench.planning.results.build_results`; kind "reproduced" when its task set matches the pin), a
    "no push" reference row per task set and kind (the tasks' start IoUs, as the first of its results files
    holds them: every planner starts from the same states), and the paper's three rows."""
    rows, start_rows = [], {}
    for path in results_files:
        r = json.loads(Path(path).read_text())
        # the planner's model grid where the results record it (a learned planner); "-" for oracle and random
        grid = "x".join(str(int(g)) for g in (r.get("planner") or {}).get("grid") or ()) or "-"
        kind = "reproduced" if r.get("pinned") else f"task set not pinned ({r.get('task_checksum', '')[:12]})"
        partial = r["coverage"]["partial"]
        tasks = r.get("per_task") or {}
        common = {"split": r["task_set"], "kind": kind, "toolkit": str(r.get("toolkit_version", "")),
                  "date": r.get("date", "")[:10], "checksum": r.get("task_checksum", "")[:12]}
        rows.append({"method": f"{r['method']} (planning)", **common,
                     "label": f"{r['coverage']['scored']}/{r['coverage']['expected']} tasks"
                              + (" (partial)" if partial else ""), "grid": grid,
                     SEQ: {t: {"planning_iou": v.get("iou")} for t, v in tasks.items()},
                     "planning_iou": r["metrics"]["iou"]})
        if (r["task_set"], kind) not in start_rows and "start_iou" in r["metrics"]:
            start_rows[(r["task_set"], kind)] = {
                "method": NO_PUSH, **common, "label": "the start state's IoU with the target", "grid": "-",
                SEQ: {t: {"planning_iou": v.get("start_iou")} for t, v in tasks.items()},
                "planning_iou": r["metrics"]["start_iou"]}
    rows += list(start_rows.values())
    if include_paper:
        rows += [{"method": m, "split": "ycb-test", "kind": "reported in the paper", "label": "Sec. 4.3",
                  "grid": "x".join(map(str, GRID_SHAPE)), "toolkit": "",
                  "date": "2020", "checksum": "", SEQ: {}, "planning_iou": v} for m, v in PLANNING_PAPER_ROWS]
    return rows


def _tables(rows: list[dict]):
    import pandas as pd

    frame = pd.DataFrame(rows)
    for (split, kind), group in frame.groupby(["split", "kind"], sort=True):
        if "planning_iou" in group and group["planning_iou"].notna().all():  # a planning task set's own table
            group = group.iloc[sorted(range(len(group)), key=lambda i: is_reference_method(group["method"].iloc[i]))]
            yield split, kind, "planning", group[["method", "grid", "planning_iou", "label", "toolkit", "date",
                                                  "checksum", SEQ]].reset_index(drop=True), ["planning_iou"]
            continue
        for track, columns in TRACKS.items():
            cols = [c for c in columns + (("planning_iou",) if track == "3D" else ()) if c in group]
            sub = group.dropna(subset=[c for c in cols if c in group], how="all")
            cols = [c for c in cols if sub[c].notna().any()]  # a column no row of this table has a value of
            if sub.empty or not cols:
                continue
            sub = sub.iloc[sorted(range(len(sub)), key=lambda i: is_reference_method(sub["method"].iloc[i]))]
            table = sub[["method", "grid", *cols, "label", "toolkit", "date", "checksum", SEQ]].reset_index(drop=True)
            yield split, kind, track, table, cols


def _difference_tables(table, track: str, cols: list[str]) -> tuple[list[str], str]:
    """Markdown and HTML of a reproduced table's paired differences: per yardstick, every other row that is not an
    oracle, row - yardstick per sequence (task), mean and standard error over the units both scored."""
    unit = "task" if track == "planning" else "sequence"
    md: list[str] = []
    page = []
    for yard in _yardsticks(table, track):
        base = table[table["method"] == yard].iloc[0]
        others = [r for _, r in table.iterrows() if r["method"] != yard and not is_oracle(r["method"])]
        if not others:
            continue
        name = yard.replace(" (planning)", "")
        cols = [c for c in cols if len(unit_values(base[SEQ], c)) >= 2]
        if not cols:
            continue
        header = ["method", *[f"{COLUMN_TITLES[c]} - {name}" for c in cols], f"{unit}s"]
        title = (f"Paired differences from {name} (row - {name}, {unit} by {unit}; mean \u00b1 standard error over "
                 f"the {unit}s both scored):")
        md += [title, "", md_row(header), "|" + "---|" * len(header)]
        html_rows = []
        for r in others:
            diffs = [paired_difference(unit_values(r[SEQ], c), unit_values(base[SEQ], c)) for c in cols]
            n = max((d.n for d in diffs), default=0)
            md.append(md_row([markdown_cell(r["method"]), *[_difference(d, c) for d, c in zip(diffs, cols)],
                               str(n)]))
            html_rows.append([(html.escape(str(r["method"])), None, ""),
                              *[(html.escape(_difference(d, c)), "" if d.n < 2 else repr(d.mean), "")
                                for d, c in zip(diffs, cols)], (str(n), str(n), "")])
        md.append("")
        page.append(f"<p class=note>{html.escape(title)}</p>" + html_table(header, html_rows, "diff"))
    return md, "".join(page)


def _version_line(split: str, kind: str, table) -> str:
    """Which version of the split a table's rows were scored on, and by which toolkit versions."""
    from dsr_bench.dataset.splits import SPLITS

    if kind == "reported in the paper":
        return ""
    checksums = sorted({c for c in table["checksum"] if c})
    toolkits = ", ".join(sorted({t for t in table["toolkit"] if t})) or "?"
    what = "task set" if split not in SPLITS or kind.startswith("task set") else "split"
    if kind == "reproduced":
        return (f"Every row was scored on this {what}'s pinned version (checksum {', '.join(checksums)}; toolkit "
                f"{toolkits}). Rows scored on another version of it are in a table of their own, never in this one.")
    return (f"These rows were scored on a {what} version that is not this toolkit's pin (checksum "
            f"{', '.join(checksums)}; toolkit {toolkits}): they are kept apart and compared with nothing else.")


def build(root: str | Path = "leaderboard", warn: Callable[[str], None] | None = None) -> tuple[Path, Path]:
    """Write README.md and index.html of the leaderboard from its valid entries and paper rows; each entry file
    that is not valid is skipped with one `warn` line naming it and its problem (default: on stderr)."""
    from dsr_bench.dataset.splits import SPLITS

    root = Path(root)
    entries = load_entries(root, warn)
    rows = load_rows(root, warn, entries)
    plotted: set[Path] = set()
    md = ["# dsr-bench leaderboard", "",
          "Built by `dsr-bench leaderboard build` from `entries/` and `planning/` (results of `dsr-bench evaluate`",
          "and `dsr-bench plan`, recomputed by `leaderboard add` from the predictions and plans) and `paper.json`",
          "(numbers reported in the paper, never mixed with reproduced rows). In each table of reproduced results the",
          "reference rows (oracle; static = predicting no motion; push = every object voxel moved along the push; in",
          "planning: no push and random pushes) sit beside the trained rows of the same version of the split.",
          "",
          "A reproduced value is the benchmark's metric \u00b1 the half-width of the 95% confidence interval of the",
          "mean over the sequences (tasks), from each row's per-sequence (per-task) values (Student t). Under each",
          "table, paired differences from the reference rows (row - reference, sequence by sequence) with their",
          "standard errors. Bold: the best value that is not an oracle's, marked only where the table holds the",
          "no-motion row to compare with; in a planning table, the best planner only where it beats both no push",
          "and random (the 95% interval of each paired difference above 0). " + _WORSE_MARK + ": worse than",
          "predicting no motion. Outside planning, bold marks the best mean, not a significant difference: the paired",
          "differences say whether two rows differ.",
          "Model grid: a 3D model's voxel grid, or the image (H x W) of an image-space model (\"-\" where the paper",
          "does not say).", ""]
    body = []
    for split, kind, track, table, cols in _tables(rows):
        md += [f"## {split}: {track} track ({kind})", ""]
        if split in SPLITS:
            md += [f"{SPLITS[split].description}.", ""]
        version = _version_line(split, kind, table)
        if version:
            md += [version, ""]
        paper = kind == "reported in the paper"
        rendered = render_table(table, track, cols, published=paper)
        comparable, inline = rendered.comparable, track == "planning"
        if not paper and not comparable:
            md += [("This table lacks the no push or the random reference row: no planner is marked best." if
                    track == "planning" else "No no-motion (static) row was scored on this version of the split: "
                    "these rows cannot be compared with predicting no motion, and none is marked best."), ""]
        md += rendered.markdown
        md.append("")
        diff_md, diff_html = _difference_tables(table, track, cols) if not paper and not inline else ([], "")
        md += diff_md
        plot = _table_plot(root, entries, split, kind, track) if track != "planning" else \
            _planning_plot(root, table, split, kind)
        figure = ""
        if plot is not None:
            plotted |= {plot, plot.with_suffix(".svg")}
            rel = plot.relative_to(root).as_posix()
            svg = plot.with_suffix(".svg").relative_to(root).as_posix()
            caption = PLANNING_CAPTION if track == "planning" else STEPS_CAPTION
            alt = f"{split}, {track} track: " + ("planning IoU and paired differences" if track == "planning" else
                                                  "per-step curves and 95% intervals")
            width = FIGURE_WIDTH_PX
            md += [caption, "", f'<img src="{rel}" width="{width}" alt="{html.escape(alt)}">', ""]
            figure = (f'<figure><a href="{html.escape(svg)}"><img src="{html.escape(svg)}" alt="{html.escape(alt)}">'
                      f"</a><figcaption>{html.escape(caption)}</figcaption></figure>")
        note = ("" if comparable or paper else
                "<p class=note>" + ("No no push or random row: no planner marked best." if track == "planning" else
                                    "No no-motion (static) row on this version of the split: not comparable, none "
                                    "marked best.") + "</p>")
        about = f"<p>{html.escape(SPLITS[split].description)}.</p>" if split in SPLITS else ""
        about += f"<p class=note>{html.escape(version)}</p>" if version else ""
        anchor = re.sub(r"[^a-z0-9]+", "-", f"{split} {track} {kind}".lower()).strip("-")  # a link to the table
        body.append(f"<h2 id=\"{anchor}\">{html.escape(split)}: {track} track ({html.escape(kind)})</h2>\n"
                    f"{about}{note}"
                    f"{rendered.html('board')}{diff_html}{figure}")
    if not rows:
        md.append("No entries yet.")
    page = _PAGE.replace("{body}", "\n".join(body) or "<p>No entries yet.</p>")
    write_text(root / "README.md", "\n".join(md) + "\n")
    write_text(root / "index.html", page)
    for stale in sorted((root / PLOTS_DIR).glob("*")):  # a plot of a table that no longer exists
        if stale.suffix in (".png", ".svg") and stale not in plotted:
            stale.unlink(missing_ok=True)
    return root / "README.md", root / "index.html"


STEPS_CAPTION = ("Top: each row step by step (reference rows dashed or dotted, open markers). Bottom: each row's "
                 "mean over the sequences with its 95% interval.")
PLANNING_CAPTION = ("Left: each row's planning IoU, mean over the tasks with its 95% interval. Right: each "
                    "planner's paired difference from no push and from random, task by task, with its 95% interval.")

#: Where `build` writes the figures, under the leaderboard's root.
PLOTS_DIR = "plots"


def plot_name(split: str, kind: str, track: str) -> str:
    """The file name of a table's figure (PNG; the SVG beside it has .svg): <split>-3d.png (-2d, -planning), or
    <split>-<checksum>-3d.png for an earlier version of the split."""
    version = "" if kind == "reproduced" else "-" + kind.rsplit(", ", 1)[-1].strip("()").rsplit(" ", 1)[-1]
    return re.sub(r"[^A-Za-z0-9._-]+", "-", f"{split}{version}") + f"-{track.lower()}.png"


def _table_plot(root: Path, entries: list[dict], split: str, kind: str, track: str) -> Path | None:
    """Write the figure of one table of reproduced rows, PNG and SVG (None: paper rows, or no entry has per-step
    values for the track)."""
    from dsr_bench.scoring.plots import MISSING_MATPLOTLIB, leaderboard_series, matplotlib_missing, \
        write_leaderboard_plot

    if not kind.startswith("reproduced"):
        return None
    panels = leaderboard_series([e for e in entries if e["split"] == split and e["kind"] == kind], track)
    if not panels:
        return None
    if matplotlib_missing():
        raise UserError(f"cannot draw {root / PLOTS_DIR}: {MISSING_MATPLOTLIB}")
    title = f"{split}: {track} track" + ("" if kind == "reproduced" else f" ({kind})")
    return write_leaderboard_plot(panels, title, root / PLOTS_DIR / plot_name(split, kind, track), svg=True)


def _planning_plot(root: Path, table, split: str, kind: str) -> Path | None:
    """Write the figure of one planning table (PNG and SVG): its rows' IoUs and paired differences (None: paper
    rows, or no row holds per-task values)."""
    from dsr_bench.scoring.plots import MISSING_MATPLOTLIB, matplotlib_missing, write_planning_plot

    if kind == "reported in the paper":
        return None
    rows = [(str(r["method"]).replace(" (planning)", ""), unit_values(r[SEQ], "planning_iou"))
            for _, r in table.iterrows()]
    rows = [(m, v) for m, v in rows if v]
    if not rows:
        return None
    if matplotlib_missing():
        raise UserError(f"cannot draw {root / PLOTS_DIR}: {MISSING_MATPLOTLIB}")
    # planners first, then the reference rows
    rows = [r for r in rows if not is_reference_method(r[0])] + [r for r in rows if is_reference_method(r[0])]
    title = f"{split}: planning track" + ("" if kind == "reproduced" else f" ({kind})")
    return write_planning_plot(rows, title, root / PLOTS_DIR / plot_name(split, kind, "planning"), svg=True)


def no_motion_entry(results: dict, root: str | Path | None = None) -> tuple[dict | None, str]:
    """The leaderboard's static (no-motion) entry scored on the same split version as `results`, with per-step
    values, for evaluate's plot; else (None, why not). `root`: the leaderboard directory (default: the one beside
    this package, in a clone of the repository)."""
    root = Path(root) if root is not None else Path(__file__).resolve().parents[2] / "leaderboard"
    if results.get("method") == NO_MOTION:
        return None, "no separate no-motion line: these results are the no-motion row's"
    if not (root / "entries").is_dir():
        return None, f"no no-motion line: no leaderboard at {root}"
    for entry in load_entries(root, warn=lambda line: None):
        if entry["method"] == NO_MOTION and entry["split"] == results.get("split") and \
                entry.get("split_checksum") == results.get("split_checksum") and entry.get("per_step"):
            return entry, ""
    return None, (f"no no-motion line: the leaderboard holds no static entry scored on this version of "
                  f"{results.get('split')!r}")


_PAGE = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>dsr-bench leaderboard</title>
<style>
body{font-family:system-ui,sans-serif;margin:2em;max-width:1100px}
table{border-collapse:collapse;margin-bottom:1.2em;font-size:14px}
th,td{border:1px solid #ccc;padding:3px 6px;text-align:right}td{white-space:nowrap}
td:first-child,th:first-child{text-align:left}th{cursor:pointer;background:#f4f4f4}.best{font-weight:bold}
.worse{color:#a00}.note{color:#555}figure{margin:0 0 2em 0}img{max-width:100%}
</style></head><body>
<h1>dsr-bench leaderboard</h1>
<p>Reproduced results (<code>dsr-bench evaluate</code>, <code>dsr-bench plan</code>) and numbers reported in the
paper, in separate tables. Reference rows (oracle; static = predicting no motion; push; in planning: no push and
random) sit beside the trained rows of the same version of a split. A reproduced value is the metric &plusmn; the
half-width of the 95% confidence interval of the mean over the sequences (tasks); under each table, paired
differences from the reference rows with their standard errors. Click a column to sort. Bold: the best value that is
not an oracle's (in planning: only a planner that beats no push and random, paired; elsewhere the best mean, not a
significant difference). &#9660; (red): worse than predicting no motion.</p>
{body}
<script>
{script}</script></body></html>
""".replace("{script}", SORT_SCRIPT)

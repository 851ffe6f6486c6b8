"""Forged results never reach the leaderboard: `leaderboard add` recomputes every number from the predictions (plans)
and refuses a file that differs, in one line, writing nothing; `leaderboard build` skips an entry file that breaks the
schema or its own consistency with one warning line and builds the rest; names are escaped and never collide; a row
is a reference row by provenance, never by a name that reads like one; JSON Python cannot read is one line too."""

import copy
import json
import shutil
from pathlib import Path

import pytest

from dsr_bench.cli import main
from dsr_bench.leaderboard.entries import check_entry, entry_name, first_difference, markdown_cell
from dsr_bench.scoring.evaluate import evaluate
from dsr_bench.testing import write_synthetic_dataset
from helpers import pin_split

ROOT = Path(__file__).resolve().parents[1]
SPLIT = "procedural-novel-mini"


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory) -> Path:
    """A 2-sequence synthetic dataset of SPLIT with static and oracle predictions."""
    data = write_synthetic_dataset(tmp_path_factory.mktemp("lb") / "data", num_sequences=2, num_steps=2, split=SPLIT)
    for model in ("static", "oracle"):
        assert main(["predict", "--model", model, "--data", str(data), "--out", str(data.parent / model)]) == 0
    return data


@pytest.fixture
def pinned(synthetic, monkeypatch) -> Path:
    """SPLIT pinned to the synthetic dataset for this test (evaluate then says "pinned": true)."""
    pin_split(monkeypatch, synthetic, SPLIT)
    return synthetic


@pytest.fixture
def root(tmp_path) -> Path:
    board = tmp_path / "leaderboard"
    board.mkdir()
    shutil.copy(ROOT / "leaderboard" / "paper.json", board / "paper.json")
    return board


def _results(pred: Path, data: Path, name: str | None = None, parameters: dict | None = None) -> dict:
    """The genuine results of a predictions directory (a copy of it when `name` or `parameters` change meta.json)."""
    if name is not None or parameters is not None:
        copy_dir = pred.parent / f"{pred.name}-{abs(hash((name, json.dumps(parameters))))}"
        if not copy_dir.exists():
            shutil.copytree(pred, copy_dir)
            meta = json.loads((copy_dir / "meta.json").read_text())
            meta.update({"name": name} if name is not None else {})
            meta.update({"parameters": parameters} if parameters is not None else {})
            (copy_dir / "meta.json").write_text(json.dumps(meta))
        pred = copy_dir
    results = evaluate(pred, data, SPLIT, workers=1).results
    assert results["pinned"] is True and results["coverage"]["partial"] is False
    return json.loads(json.dumps(results)) | {"_pred": str(pred)}


def _snapshot(board: Path) -> dict:
    return {p.relative_to(board).as_posix(): p.read_bytes() for p in sorted(board.rglob("*")) if p.is_file()}


def _add(board: Path, results, tmp_path: Path, capsys, *extra: str, raw: str | None = None) -> tuple[int, str, str]:
    """`leaderboard add` from the CLI of a results dict (its "_pred" key: the predictions) or raw text."""
    pred = results.pop("_pred", None) if isinstance(results, dict) else None
    path = tmp_path / "submitted.json"
    path.write_text(raw if raw is not None else json.dumps(results))
    capsys.readouterr()
    args = ["leaderboard", "add", str(path), "--root", str(board), *(["--predictions", pred] if pred else []), *extra]
    rc = main(args)
    captured = capsys.readouterr()
    return rc, captured.out, captured.err


def _nan_metric(r):
    text = json.dumps(r).replace(f'"motion_full": {json.dumps(r["metrics"]["motion_full"])}', '"motion_full": NaN', 1)
    return text


#: every forged 3D results file of the issue: (name, edit of the genuine results, a word the refusal names)
FORGED = [
    ("edited number", lambda r: r["metrics"].update(iou_ordered=0.93), "metrics.iou_ordered is 0.93"),
    ("edited with its per-step and per-sequence values", lambda r: (
        r["metrics"].update(iou_ordered=0.9), r["per_step"].update(iou_ordered=[0.9] * 2),
        [s.update(iou_ordered=0.9) for s in r["per_sequence"].values()]), "metrics.iou_ordered is 0.9 "),
    ("IoU 1.7", lambda r: r["metrics"].update(iou_unordered=1.7), "metrics.iou_unordered is 1.7"),
    ("MSE -5", lambda r: r["metrics"].update(motion_visible=-5), "metrics.motion_visible is -5"),
    ("inf", lambda r: r["metrics"].update(motion_full=float("inf")), "metrics.motion_full is Infinity"),
    ("coverage 1/2 with partial false", lambda r: r["coverage"].update(scored=1), "coverage.scored is 1"),
    ("no coverage", lambda r: r.pop("coverage"), "coverage is missing"),
    ("pinned false beside the pinned checksum", lambda r: r.update(pinned=False), "pinned is false"),
    ("ground truth said unverified", lambda r: r.update(ground_truth_verified=False), "ground_truth_verified"),
    ("predictions checksum of other predictions", lambda r: r.update(predictions_checksum="0" * 64),
     "predictions_checksum is"),
    ("split checksum zeroed", lambda r: r.update(split_checksum="0" * 64), "split_checksum is"),
    ("cut down to motion_2d", lambda r: r.update(
        metrics={"motion_2d": r["metrics"]["motion_2d"]}, per_step={"motion_2d": r["per_step"]["motion_2d"]},
        per_sequence={k: {"motion_2d": v["motion_2d"]} for k, v in r["per_sequence"].items()}, breakdowns={}),
     "metrics.iou_ordered is missing"),
    ("an extra metric", lambda r: r["metrics"].update(iou_bonus=1.0), "metrics.iou_bonus is 1.0 but"),
    ("a sequence removed", lambda r: r["per_sequence"].pop("seq_0001"), "per_sequence.seq_0001 is missing"),
    ("another method's name", lambda r: r.update(method="oracle"), "method is \"oracle\" but"),
    ("grid of strings", lambda r: r["meta"].update(parameters={"grid": ["a", "b"]}), "meta.parameters"),
    ("date 12", lambda r: r.update(date=12), "date is 12, not a string"),
    ("label a number", lambda r: r.update(label=7), "label is 7, not a string"),
]


@pytest.mark.parametrize("name, edit, named", FORGED, ids=[f[0] for f in FORGED])
def test_a_forged_results_file_is_refused_in_one_line_and_nothing_is_written(pinned, root, tmp_path, capsys, name,
                                                                             edit, named):
    genuine = _results(pinned.parent / "static", pinned)
    forged = copy.deepcopy(genuine)
    edit(forged)
    before = _snapshot(root)
    rc, out, err = _add(root, forged, tmp_path, capsys)
    assert rc == 2 and out == "" and len(err.splitlines()) == 1 and err.startswith("error: "), err
    assert named in err, err
    assert _snapshot(root) == before


def test_nan_a_relabelled_split_a_json_list_and_no_predictions_are_refused(pinned, root, tmp_path, capsys):
    from dsr_bench.dataset.splits import SPLITS

    genuine = _results(pinned.parent / "static", pinned)
    pred = genuine.pop("_pred")
    other = SPLITS["cpu-novel-test"].expected_digest
    relabelled = {**copy.deepcopy(genuine), "split": "cpu-novel-test", "split_checksum": other,
                  "coverage": {"scored": 100, "expected": 100, "partial": False}}
    cases = [  # (results, raw text, --predictions, what the refusal names)
        ({}, _nan_metric(genuine), pred, "metrics.motion_full is NaN"),
        (relabelled, None, pred, "cpu-novel-test"),
        ([genuine["metrics"]], None, pred, "not a dsr-bench results file"),
        ({}, json.dumps(genuine)[:100], pred, "unreadable results file"),
        (genuine, None, None, "give --predictions PRED_DIR"),
    ]
    before = _snapshot(root)
    for results, raw, predictions, named in cases:
        extra = ("--predictions", predictions) if predictions else ()
        rc, out, err = _add(root, results, tmp_path, capsys, *extra, raw=raw)
        assert rc == 2 and len(err.splitlines()) == 1 and named in err, (named, err)
    assert _snapshot(root) == before
    # relabelled files, checked alone as `build` checks a file in entries/
    assert any("per_sequence holds 2" in p for p in check_entry(relabelled))
    assert check_entry({**genuine, "split": "cpu-novel-test"}) == [
        "split_checksum is the pin of procedural-novel-mini, not of cpu-novel-test (a result relabelled as another "
        "split)"]
    assert check_entry(genuine) == []
    # a validation split is where training choices are made: a result on it is never ranked, whatever it holds
    assert check_entry({**genuine, "split": "cpu-val"}) == [
        "split 'cpu-val' is a validation split (where training choices are made); it is never ranked: score a test "
        "split"]


def test_a_genuine_submission_is_recomputed_written_and_replaced_only_by_itself(pinned, root, tmp_path, capsys):
    genuine = _results(pinned.parent / "static", pinned)
    submitted = {k: v for k, v in genuine.items() if k != "_pred"}
    rc, out, err = _add(root, {**genuine, "date": "2020-01-01T00:00:00Z"}, tmp_path, capsys, "--label", "reference")
    assert rc == 0 and err == "" and out.startswith("added ")
    (entry,) = (root / "entries").iterdir()
    written = json.loads(entry.read_text())
    assert written["label"] == "reference" and written["date"] != "2020-01-01T00:00:00Z"  # the recomputed results
    assert first_difference(submitted, written) is None and check_entry(written) == []
    assert entry.name == entry_name(written) and entry.name.startswith("static-procedural-novel-mini-")
    md = (root / "README.md").read_text()
    assert "| static | 128x128x48 |" in md and "reference" in md
    # the same method, split and predictions again: its own file replaced, and said
    rc, out, _ = _add(root, genuine, tmp_path, capsys)
    assert rc == 0 and out.startswith(f"replaced {entry}") and [p.name for p in (root / "entries").iterdir()] == [
        entry.name]


def test_names_never_collide_and_are_escaped_in_the_tables(pinned, root, tmp_path, capsys):
    static = pinned.parent / "static"
    assert _add(root, _results(static, pinned), tmp_path, capsys, "--label", "reference (no training)")[0] == 0
    (reference,) = (root / "entries").iterdir()
    legacy = reference.rename(root / "entries" / "static-procedural-novel-mini.json")  # the repository's naming
    kept = legacy.read_bytes()
    hostile = "a|b <img src=x onerror=alert(1)>\n**0.999**"
    for name, pred in (("stationary", static), (hostile, static)):  # (`Static!` reads as static: refused, below)
        rc, out, err = _add(root, _results(pred, pinned, name=name), tmp_path, capsys)
        assert rc == 0 and out.startswith("added "), err
    # a reference row's name on other predictions: the no-motion yardstick would be spoofed
    rc, out, err = _add(root, _results(pinned.parent / "oracle", pinned, name="static"), tmp_path, capsys)
    assert rc == 2 and "named like the reference row 'static'" in err and len(err.strip().splitlines()) == 1
    assert legacy.read_bytes() == kept  # never overwritten by another method, nor by `static` on other predictions
    assert len(list((root / "entries").iterdir())) == 3
    rc, out, _ = _add(root, _results(static, pinned), tmp_path, capsys, "--label", "reference (no training)")
    assert rc == 0 and out.startswith(f"replaced {legacy}")  # the same method, split and predictions: its own file
    md = (root / "README.md").read_text()
    table = md.split(f"## {SPLIT}: 3D track (reproduced)")[1].split("## ")[0].split("\n| method |")[1]
    rows = ["| method |" + table.split("\n\n")[0].splitlines()[0]] + [
        line for line in table.split("\n\n")[0].splitlines() if line.startswith("| ")]  # the table, not its pairs
    assert len(rows) == 1 + 3 and len({line.replace("\\|", "").count("|") for line in rows}) == 1  # cells intact
    row = next(line for line in rows if "onerror" in line)
    assert row.startswith("| a\\|b &lt;img src=x onerror=alert(1)&gt; \\*\\*0.999\\*\\* |")
    assert "<img src=x" not in md  # the only images are the build's own figures
    assert "<img src=x" not in (root / "index.html").read_text()
    assert markdown_cell("short_schedule.py _x_ `c`") == "short_schedule.py \\_x\\_ \\`c\\`"


#: names that read as a reference row without being it (the row named): look-alike letters (Cyrillic, Greek),
#: invisible characters, NBSP, case, punctuation, a track suffix or note, an alias, another track's reference row
LOOK_ALIKES = [("\u0455tatic", "static"), ("st\u200batic", "static"), ("s\u00a0tatic", "static"),
               ("STATIC", "static"), ("Static!", "static"), ("static-cpu", "static"), ("Static (mine)", "static"),
               ("No motion", "static"), ("\u03bfr\u0430cle", "oracle"), ("\u0420ush", "push"),
               ("random", "random"), ("no push", "no push")]


def test_a_look_alike_of_a_reference_row_is_refused_and_never_shown_as_one(pinned, root, tmp_path, capsys):
    """Oracle predictions whose meta.json names them `st\u0430tic` (a Cyrillic a) are refused in one line, nothing
    written; so is every other way of writing a reference row's name; an entry file holding one (an older toolkit's,
    or one placed by hand) is skipped by `build` with one warning, never shown (as a trained row of 0 / 0 / 1 / 1)."""
    lookalike = "st\u0430tic"
    results = _results(pinned.parent / "oracle", pinned, name=lookalike)
    entry = {k: v for k, v in results.items() if k != "_pred"}
    before = _snapshot(root)
    rc, out, err = _add(root, results, tmp_path, capsys)
    assert rc == 2 and out == "" and len(err.splitlines()) == 1, err
    assert "reads as the reference row 'static'" in err and "meta.json's name" in err
    genuine = _results(pinned.parent / "oracle", pinned)
    for name, row in LOOK_ALIKES:
        rc, out, err = _add(root, {**genuine, "method": name}, tmp_path, capsys)
        assert rc == 2 and len(err.splitlines()) == 1 and f"reference row {row!r}" in err, (name, err)
    rc, out, err = _add(root, {**genuine, "method": "\u202estatic"}, tmp_path, capsys)  # a bidi override
    assert rc == 2 and len(err.splitlines()) == 1 and "bidi control U+202E" in err, err
    assert _snapshot(root) == before
    (root / "entries").mkdir()
    (root / "entries" / "lookalike.json").write_text(json.dumps(entry))
    assert main(["leaderboard", "build", "--root", str(root)]) == 0
    warnings = capsys.readouterr().err.splitlines()
    assert len(warnings) == 1 and "lookalike.json" in warnings[0] and "reference row 'static'" in warnings[0]
    md = (root / "README.md").read_text()
    assert lookalike not in md and f"## {SPLIT}" not in md


def test_a_name_that_reads_like_another_entrys_is_refused(pinned, root, tmp_path, capsys):
    """A method named like an entry already on the leaderboard (look-alike letters, case, spaces, punctuation,
    invisible characters aside) without being its exact name is refused in one line; the exact name is that method
    (other predictions of it: an entry of their own)."""
    assert _add(root, _results(pinned.parent / "static", pinned, name="my-model"), tmp_path, capsys)[0] == 0
    oracle = pinned.parent / "oracle"
    rc, out, err = _add(root, _results(oracle, pinned, name="m\u0443-model"), tmp_path, capsys)  # Cyrillic u
    assert rc == 2 and len(err.splitlines()) == 1 and "reads like the entry 'my-model'" in err, err
    genuine = _results(oracle, pinned)
    for name in ("My Model", "my_model", "my-model\u200b", "m\u0443-m\u043ed\u0435l"):
        rc, out, err = _add(root, {**genuine, "method": name}, tmp_path, capsys)
        assert rc == 2 and len(err.splitlines()) == 1 and "reads like the entry 'my-model'" in err, (name, err)
    assert len(list((root / "entries").iterdir())) == 1
    rc, out, err = _add(root, _results(oracle, pinned, name="my-model"), tmp_path, capsys)
    assert rc == 0 and out.startswith("added "), err
    assert len(list((root / "entries").iterdir())) == 2


def test_json_python_cannot_read_is_one_line_naming_the_file(root, tmp_path, capsys):
    """A results file holding a 5000-digit integer (past Python's int conversion limit) or nested 100,000 deep is
    refused by `add` in one line naming it; entry files like them are skipped by `build` with one warning each."""
    huge = '{"format": "dsr-bench-results", "version": ' + "7" * 5000 + "}"
    deep = "[" * 100_000 + "]" * 100_000
    for raw, why in ((huge, "an integer of more than"), (deep, "nested deeper")):
        rc, out, err = _add(root, {}, tmp_path, capsys, "--predictions", str(tmp_path), raw=raw)
        assert rc == 2 and len(err.splitlines()) == 1 and "submitted.json: unreadable results file" in err, err
        assert why in err
    plans = tmp_path / "plans"  # a plan run's own results.json, which `add --plans` reads too
    plans.mkdir()
    (plans / "results.json").write_text(deep)
    rc, out, err = _add(root, {"format": "dsr-bench-plan-results"}, tmp_path, capsys, "--plans", str(plans))
    assert rc == 2 and len(err.splitlines()) == 1 and "plans/results.json: unreadable results file" in err, err
    (root / "entries").mkdir()
    (root / "planning").mkdir()
    (root / "entries" / "huge.json").write_text(huge)
    (root / "planning" / "deep.json").write_text(deep)
    assert main(["leaderboard", "build", "--root", str(root)]) == 0
    warnings = capsys.readouterr().err.splitlines()
    assert len(warnings) == 2 and all(w.startswith("warning: skipped ") for w in warnings)
    assert "huge.json: an integer of more than" in warnings[0] and "deep.json: JSON nested deeper" in warnings[1]


def test_meta_json_that_would_break_the_tables_is_refused(pinned, root, tmp_path, capsys):
    """Genuine results whose meta.json (the submitter's) holds a grid of strings: refused before anything is written."""
    results = _results(pinned.parent / "static", pinned, parameters={"grid": ["a", "b"]})
    rc, _, err = _add(root, results, tmp_path, capsys)
    assert rc == 2 and "meta.parameters.grid is" in err and not (root / "entries").exists()


def test_build_skips_every_bad_entry_with_one_warning_and_builds_the_rest(pinned, root, tmp_path, capsys):
    assert _add(root, _results(pinned.parent / "static", pinned), tmp_path, capsys)[0] == 0
    (good,) = (root / "entries").iterdir()
    genuine = json.loads(good.read_text())
    bad = {"date-12.json": json.dumps({**genuine, "date": 12}),
           "grid-strings.json": json.dumps({**genuine, "meta": {"parameters": {"grid": ["a", "b"]}}}),
           "a-list.json": "[1, 2]", "truncated.json": good.read_text()[:50],
           "iou-1.7.json": json.dumps({**genuine, "metrics": {**genuine["metrics"], "iou_ordered": 1.7}}),
           "unpinned.json": json.dumps({**genuine, "pinned": False}),
           "metric-off-its-steps.json": json.dumps({**genuine, "metrics": {**genuine["metrics"], "iou_ordered": 0.5}}),
           "plan.json": json.dumps({"format": "dsr-bench-plan-results"})}
    for name, text in bad.items():
        (root / "entries" / name).write_text(text)
    (root / "planning").mkdir()
    plan = json.loads(next((ROOT / "leaderboard" / "planning").glob("random-plan-novel-test*.json")).read_text())
    bad_plans = {"forged.json": {"format": "dsr-bench-plan-results", "metrics": {}},
                 "task-set-a-list.json": {**plan, "task_set": ["plan-novel-test"]},
                 "planner-grid.json": {**plan, "planner": {**plan["planner"], "grid": ["a", "b", "c"]}},
                 "iou-1.5.json": {**plan, "metrics": {**plan["metrics"], "iou": 1.5}}}
    for name, results in bad_plans.items():
        (root / "planning" / name).write_text(json.dumps(results))
    (root / "planning" / "random.json").write_text(json.dumps(plan))  # valid: built
    capsys.readouterr()
    assert main(["leaderboard", "build", "--root", str(root)]) == 0
    warnings = capsys.readouterr().err.splitlines()
    assert len(warnings) == len(bad) + len(bad_plans) and all(w.startswith("warning: skipped ") for w in warnings)
    for name in [*bad, *bad_plans]:
        assert sum(f"/{name}:" in w for w in warnings) == 1, name
    md = (root / "README.md").read_text()
    assert md.count("| static |") == 2  # the good entry, in the 3D and the 2D table; every bad one left out
    assert md.count("| random (planning) |") == 1
    rc, out, err = _add(root, _results(pinned.parent / "oracle", pinned), tmp_path, capsys)  # a later add works
    assert rc == 0 and out.startswith("added ") and err.count("warning: skipped ") == len(bad) + len(bad_plans)


def test_the_repository_leaderboard_is_valid_and_builds_unchanged(tmp_path):
    board = tmp_path / "lb"
    shutil.copytree(ROOT / "leaderboard", board)
    warnings = []
    from dsr_bench.leaderboard.board import build

    md, page = build(board, warn=warnings.append)
    assert warnings == []
    assert md.read_text() == (ROOT / "leaderboard" / "README.md").read_text()
    assert page.read_text() == (ROOT / "leaderboard" / "index.html").read_text()


# --- planning results -----------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def plan_run(tmp_path_factory) -> tuple[Path, Path]:
    """The four pinned plan-novel-mini tasks and a random planner's complete run on them."""
    pytest.importorskip("pybullet")
    base = tmp_path_factory.mktemp("plans")
    assert main(["generate-plan-tasks", "--tasks", "plan-novel-mini", "--out", str(base / "tasks")]) == 0
    assert main(["plan", "--model", "random", "--tasks", str(base / "tasks"), "--out", str(base / "random")]) == 0
    return base / "tasks", base / "random"


def _mean_one(r):
    for t in r["per_task"].values():
        t.update(iou=1.0)
    r["metrics"].update(iou=1.0, planning_iou=1.0)


def _keep(r, n):
    r["per_task"] = dict(list(r["per_task"].items())[:n])


PLAN_FORGED = [
    ("per-task values and mean edited to 1.0", _mean_one, "metrics.iou is 1.0 but the plans score"),
    ("mean off its per-task values", lambda r: r["metrics"].update(iou=0.99), "metrics.iou is 0.99"),
    ("tasks removed", lambda r: _keep(r, 2), "per_task.task_0002 is missing"),
    ("per_task empty", lambda r: _keep(r, 0), "per_task.task_0000 is missing"),
    ("coverage 1/4 with partial false", lambda r: r["coverage"].update(scored=1), "coverage.scored is 1"),
    ("task checksum zeroed, pinned true", lambda r: r.update(task_checksum="0" * 64, split_checksum="0" * 64),
     "split_checksum is \"0000"),
    ("plan-novel-mini relabelled plan-novel-test", lambda r: r.update(
        task_set="plan-novel-test", split="plan-novel-test", coverage={"scored": 4, "expected": 100, "partial": True}),
     "split is \"plan-novel-test\" but the plans score \"plan-novel-mini\""),
    ("date 12", lambda r: r.update(date=12), "date is not a string"),
]


@pytest.mark.parametrize("name, edit, named", PLAN_FORGED, ids=[f[0] for f in PLAN_FORGED])
def test_forged_planning_results_are_refused_in_one_line_and_nothing_is_written(plan_run, root, tmp_path, capsys,
                                                                                name, edit, named):
    tasks, plans = plan_run
    forged = json.loads((plans / "results.json").read_text())
    edit(forged)
    path = tmp_path / "plan-results.json"
    path.write_text(json.dumps(forged))
    before = _snapshot(root)
    capsys.readouterr()
    assert main(["leaderboard", "add", str(path), "--plans", str(plans), "--tasks", str(tasks), "--root",
                 str(root)]) == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and named in err, err
    assert _snapshot(root) == before


def test_genuine_planning_results_are_recomputed_and_written(plan_run, root, tmp_path, capsys):
    from dsr_bench.planning.verify import recompute_results

    tasks, plans = plan_run
    capsys.readouterr()
    assert main(["leaderboard", "add", str(plans / "results.json"), "--root", str(root)]) == 2  # no --plans
    assert "give --plans PLANS_DIR" in capsys.readouterr().err and not (root / "planning").exists()
    args = ["leaderboard", "add", str(plans / "results.json"), "--plans", str(plans), "--tasks", str(tasks),
            "--root", str(root)]
    assert main(args) == 0 and capsys.readouterr().out.startswith("added ")
    (entry,) = (root / "planning").iterdir()
    written = json.loads(entry.read_text())
    assert first_difference(written, recompute_results(plans, tasks), "plans") is None and check_entry(written) == []
    assert "| random (planning) |" in (root / "README.md").read_text()
    assert main(args) == 0 and capsys.readouterr().out.startswith(f"replaced {entry}")


def _forged_plans(plans: Path, tasks: Path, out: Path, edit) -> Path:
    """A copy of a plan run whose plan files `edit` changed, with the results.json a forger would write for them (the
    run's own, its method and planner those the changed files name)."""
    import h5py

    shutil.copytree(plans, out)
    for plan in sorted(out.glob("*.h5")):
        with h5py.File(plan, "r+") as f:
            edit(f)
            planner, description = str(f.attrs["planner"]), str(f.attrs["description"])
    results = json.loads((out / "results.json").read_text())
    results["method"] = results["planner"]["name"] = planner
    results["planner"]["description"] = description
    (out / "results.json").write_text(json.dumps(results))
    return out


def _as_random(f) -> None:
    """A plan file relabelled as the random planner's (its planner name and description)."""
    from dsr_bench.planning.planners import RandomPlanner

    f.attrs["planner"], f.attrs["description"] = "random", RandomPlanner.description


def test_planning_reference_rows_are_so_by_provenance(plan_run, root, tmp_path, capsys):
    """Planning results whose plan files name the planner like a reference row (`r\u0430ndom`, `no push`) are refused
    in one line; the oracle planner's genuine plans relabelled random (every score genuine) are refused too: the
    planner they name is not the model that made them (and a replay as random's would find other pushes than the ones
    random draws from the seeds); nothing is written."""
    tasks, plans = plan_run
    oracle = tmp_path / "oracle"
    assert main(["plan", "--model", "oracle", "--tasks", str(tasks), "--out", str(oracle), "--candidates", "3"]) == 0
    cases = [(plans, lambda f: f.attrs.__setitem__("planner", "r\u0430ndom"), "reads as the reference row 'random'"),
             (plans, lambda f: f.attrs.__setitem__("planner", "no push"), "reference row 'no push'"),
             (oracle, _as_random, "its planner 'random' was not made by the model 'oracle' it records")]
    before = _snapshot(root)
    for i, (run, edit, named) in enumerate(cases):
        forged = _forged_plans(run, tasks, tmp_path / f"forged-{i}", edit)
        capsys.readouterr()
        assert main(["leaderboard", "add", str(forged / "results.json"), "--plans", str(forged), "--tasks", str(tasks),
                     "--root", str(root)]) == 2
        err = capsys.readouterr().err
        assert len(err.splitlines()) == 1 and named in err, err
    assert _snapshot(root) == before


def test_a_results_file_of_another_toolkit_version_is_refused_not_rewritten(plan_run, root, tmp_path, capsys):
    """The issue's case: `toolkit_version` edited to 9.9.9 was accepted and quietly rewritten, though the help says
    the file must equal the recomputation in every field but the date: now it is one line naming the field, and
    nothing is written."""
    tasks, plans = plan_run
    forged = tmp_path / "plans"
    shutil.copytree(plans, forged)
    results = json.loads((forged / "results.json").read_text())
    (forged / "results.json").write_text(json.dumps({**results, "toolkit_version": "9.9.9"}))
    before = _snapshot(root)
    capsys.readouterr()
    assert main(["leaderboard", "add", str(forged / "results.json"), "--plans", str(forged), "--tasks", str(tasks),
                 "--root", str(root)]) == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and "toolkit_version is \"9.9.9\"" in err, err
    assert _snapshot(root) == before

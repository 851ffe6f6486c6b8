"""The planning track never trusts its files (`dsr_bench.planning.verify`): a corpus of forged task files, plan files
and results files, each refused with one line, scored as `"pinned": false`, planned again, or reported by
`check_results` / `recompute_results`. One honest run of the random planner on plan-novel-mini (4 pinned tasks) is
the material; every case edits a copy of it."""

import json
import shutil

import h5py
import numpy as np
import pytest

from dsr_bench.errors import UserError


@pytest.fixture(scope="module")
def mini(tmp_path_factory):
    """plan-novel-mini's 4 tasks (pinned) and an honest random run on them: (tasks, plans, results)."""
    pytest.importorskip("pybullet")
    from dsr_bench.cli import main

    root = tmp_path_factory.mktemp("forged")
    assert main(["generate-plan-tasks", "--tasks", "plan-novel-mini", "--out", str(root / "tasks")]) == 0
    assert main(["plan", "--model", "random", "--tasks", str(root / "tasks"), "--out", str(root / "plans")]) == 0
    return root / "tasks", root / "plans", json.loads((root / "plans" / "results.json").read_text())


@pytest.fixture
def copy(mini, tmp_path):
    """A writable copy of the honest run: (tasks, plans, results)."""
    tasks, plans, results = mini
    shutil.copytree(tasks, tmp_path / "tasks")
    shutil.copytree(plans, tmp_path / "plans")
    return tmp_path / "tasks", tmp_path / "plans", results


def _plan(capsys, tasks, out, *extra):
    """`dsr-bench plan --model random` in this process: (exit code, stdout, the stderr lines)."""
    from dsr_bench.cli import main

    capsys.readouterr()
    code = main(["plan", "--model", "random", "--tasks", str(tasks), "--out", str(out), *extra])
    captured = capsys.readouterr()
    return code, captured.out, [line for line in captured.err.splitlines() if line.strip()]


def _forge_task(path, edit):
    """Edit a task file's arrays and write its own digests anew, as a forger would."""
    from dsr_bench.planning.tasks import task_digests

    with h5py.File(path, "a") as f:
        edit(f)
        arrays = {}
        f.visititems(lambda name, obj: arrays.__setitem__(name, obj[()]) if isinstance(obj, h5py.Dataset) else None)
        for key, value in task_digests(arrays, json.loads(f.attrs["objects"])).items():
            f.attrs[key] = value


def _set_attr(path, key, value):
    with h5py.File(path, "a") as f:
        f.attrs[key] = value


def _scores(results):
    return {name: {k: v for k, v in t.items() if k != "seconds"} for name, t in results["per_task"].items()}


def test_an_honest_run_recomputes_to_its_results_exactly(mini):
    from dsr_bench.planning.verify import check_results, recompute_results, verify_tasks

    tasks, plans, results = mini
    assert results["pinned"] is True and results["coverage"] == {"scored": 4, "expected": 4, "partial": False}
    assert verify_tasks(tasks).warnings == () and verify_tasks(tasks).pinned
    assert recompute_results(plans, tasks) == results  # every field, bit for bit
    assert check_results(results) == []


def test_a_task_edited_with_its_own_digests_recomputed_is_not_pinned(copy, capsys):
    """The issue's case: task_0001's target set to its start, the file's digests recomputed (tasks.json left, then
    rebuilt too): one warning naming the task, "pinned": false, and the old plan of the genuine task planned again."""
    from dsr_bench.planning.tasks import build_manifest, write_manifest
    from dsr_bench.planning.verify import check_results, recompute_results

    tasks, plans, honest = copy
    _forge_task(tasks / "task_0001.h5", lambda f: f["target/mask_3d"].write_direct(f["start/mask_3d"][()]))
    for rebuild_manifest in (False, True):
        if rebuild_manifest:
            write_manifest(tasks, build_manifest(tasks, "plan-novel-mini", [f"task_000{i}" for i in range(4)]))
        code, out, err = _plan(capsys, tasks, plans)
        assert code == 0 and "(4/4 tasks)" in out and "pinned" not in out
        pin_lines = [line for line in err if "differs from the pin" in line]
        assert len(pin_lines) == 1 and "task_0001.h5" in pin_lines[0] and '"pinned": false' in pin_lines[0]
        results = json.loads((plans / "results.json").read_text())
        assert results["pinned"] is False and results["task_checksum"] != honest["task_checksum"]
        assert check_results(results) == [] and recompute_results(plans, tasks) == results
    assert results["per_task"]["task_0001"]["start_iou"] == 1.0  # its start scored against itself: the forged task


def test_resume_never_takes_a_stored_score_for_the_replayed_one(copy, capsys):
    """The issue's case: a plan file's stored iou set to 0.99 gave 0.5057 on a rerun. The stored scores are never
    read as scores: the rerun replays the plan, finds the record edited (one warning), plans the task again and
    gives the honest result."""
    from dsr_bench.planning.verify import recompute_results

    tasks, plans, honest = copy
    for key in ("iou", "iou_identity", "iou_occupancy", "start_iou"):
        _set_attr(plans / "task_0000.h5", key, 0.99)
    with pytest.raises(UserError, match=r"task_0000.h5: its stored iou is not the score of its replayed final state"):
        recompute_results(plans, tasks)
    code, out, err = _plan(capsys, tasks, plans)
    assert code == 0 and f"(4/4 tasks, pinned): IoU {honest['metrics']['iou']:.4f}" in out
    assert len(err) == 1 and "task_0000.h5: its stored iou is not the score" in err[0]
    assert err[0].endswith("planned again")
    results = json.loads((plans / "results.json").read_text())
    assert _scores(results) == _scores(honest) and results["metrics"]["iou"] == honest["metrics"]["iou"]
    assert recompute_results(plans, tasks) == results


def _edit_plan(path, edit):
    with h5py.File(path, "a") as f:
        edit(f)


def _set_row(f, name, index, value):
    data = f[name][()]
    data[index] = value
    f[name].write_direct(data)


def test_a_forged_final_state_survives_neither_a_resume_nor_recompute(copy, capsys):
    """The issue's case: task_0000's stored final state (masks and poses) set to the target's, results.json deleted
    and the same command run: IoU 0.2624 -> 0.3806, "pinned": true, and `leaderboard add` took it. Now every stored
    state is compared with the replay of the plan's executed pushes: refused by recompute, planned again by plan."""
    from dsr_bench.planning.tasks import read_task
    from dsr_bench.planning.verify import recompute_results

    tasks, plans, honest = copy
    task = read_task(tasks / "task_0000.h5")

    def forge(f):
        _set_row(f, "states/mask_3d", 3, task.target_mask)
        _set_row(f, "states/object_poses", 3, task.arrays["target/object_poses"])
    _edit_plan(plans / "task_0000.h5", forge)
    with pytest.raises(UserError, match=r"task_0000.h5: states/object_poses\[3\] is not what the task's start and "
                                        r"the plan's executed pushes give when replayed") as e:
        recompute_results(plans, tasks)
    assert "\n" not in str(e.value)
    (plans / "results.json").unlink()
    code, out, err = _plan(capsys, tasks, plans)
    assert code == 0 and f"(4/4 tasks, pinned): IoU {honest['metrics']['iou']:.4f}" in out
    assert len(err) == 1 and "task_0000.h5: states/object_poses[3] is not what" in err[0]
    results = json.loads((plans / "results.json").read_text())
    assert _scores(results) == _scores(honest) and recompute_results(plans, tasks) == results


@pytest.mark.parametrize("forge, message", [
    ("action", "states/object_poses[1] is not what the task's start and the plan's executed pushes give"),
    ("mask only", "states/mask_3d[2] is not what the task's start"),
    ("tsdf", "states/tsdf[1] is not what"),
    ("color", "states/color[3] is not what"),
    ("candidate", "step 0: its candidates are not the ones its seeds draw around its planner masks"),
    ("chosen", "step 1: the executed push is not the candidate it says it chose"),
    ("seed", "task_0002.h5 was made with seed 1, task_0000.h5 with 0: not one run's plans"),
    ("cost", "step 2: a random plan with costs, masks or a prediction"),
    ("per-object iou", "its stored iou_per_object is not the score of its replayed final state"),
])
def test_every_edit_of_a_plan_file_is_caught_by_its_replay(copy, forge, message):
    """Byte edits that change no score (an executed push moved back to where it came from, a TSDF voxel, a pixel, a
    candidate, the stored per-object IoUs) and edits that would (a state, an action): each refused in one line by
    `recompute_results` (what `leaderboard add --plans` runs)."""
    from dsr_bench.planning.verify import recompute_results

    tasks, plans, _ = copy
    path = plans / ("task_0002.h5" if forge == "seed" else "task_0001.h5")

    def edit(f):
        if forge == "action":  # another push, with its candidate and the record of it changed alike
            action = f["actions"][0] + np.array([0, 1, 0])
            _set_row(f, "actions", 0, action)
            _set_row(f, "candidates", (0, 0), action)
        elif forge == "mask only":
            _set_row(f, "states/mask_3d", (2, 0, 0, 0), 1)
        elif forge == "tsdf":
            _set_row(f, "states/tsdf", (1, 64, 64, 40), 0.5)
        elif forge == "color":
            _set_row(f, "states/color", (3, 0, 0, 0), 7)
        elif forge == "candidate":
            _set_row(f, "candidates", (0, 0, 1), (f["candidates"][0, 0, 1] + 1) % 128)
        elif forge == "chosen":
            f["chosen"].write_direct(f["chosen"][()] + np.array([0, 1, 0]))
        elif forge == "seed":
            f.attrs["seed"] = 1
        elif forge == "cost":
            _set_row(f, "costs", (2, 0), -1.0)
        else:
            f.attrs["iou_per_object"] = json.dumps([1.0] * 4)
    _edit_plan(path, edit)
    with pytest.raises(UserError, match=re_escape(message)) as e:
        recompute_results(plans, tasks)
    assert "\n" not in str(e.value)


def re_escape(text):
    import re

    return re.escape(text)


def test_a_task_seed_edited_by_one_byte_is_refused_before_planning(copy, capsys):
    """The issue's case: one byte of task_0001.h5's seed attribute (not covered by the task digests) reseeded the
    candidates: 0.2624 -> 0.3378, still "pinned": true. A named set's seed is derived from the set: one line, exit 2,
    nothing written; recompute refuses the directory too."""
    from dsr_bench.planning.verify import recompute_results

    tasks, plans, _ = copy
    with h5py.File(tasks / "task_0001.h5", "a") as f:
        f.attrs["seed"] = int(f.attrs["seed"]) ^ 0x100
    out = plans.parent / "fresh"
    code, stdout, err = _plan(capsys, tasks, out)
    assert code == 2 and len(err) == 1 and stdout.strip() == "" and not out.exists()
    assert "task_0001.h5: its seed attribute" in err[0] and "is not the seed of plan-novel-mini task_0001" in err[0]
    with pytest.raises(UserError, match="task_0001.h5: its seed attribute"):
        recompute_results(plans, tasks)


def test_a_plan_file_of_another_task_is_planned_again_and_refused_by_recompute(copy, capsys):
    """The issue's case: one changed byte in a plan's task name made task_0001's score replace task_0000's
    ("3/4 tasks, pinned"); now the rerun plans task_0001 again (one warning) and scores 4/4 honestly."""
    from dsr_bench.planning.verify import recompute_results

    tasks, plans, honest = copy
    _set_attr(plans / "task_0001.h5", "task", "task_0000")
    with pytest.raises(UserError, match=r"task_0001.h5: a plan of task_0000, not of the task it is named for") as e:
        recompute_results(plans, tasks)
    assert "\n" not in str(e.value)
    code, out, err = _plan(capsys, tasks, plans)
    assert code == 0 and "(4/4 tasks, pinned)" in out
    assert len(err) == 1 and "task_0001.h5: a plan of task_0000" in err[0] and err[0].endswith("planned again")
    results = json.loads((plans / "results.json").read_text())
    assert _scores(results) == _scores(honest)  # the random planner's plan is a pure function of its seeds
    assert recompute_results(plans, tasks) == results
    shutil.copy(plans / "task_0000.h5", plans / "task_0001.h5")  # a whole plan file under another task's name
    with pytest.raises(UserError, match="a plan of task_0000, not of the task it is named for"):
        recompute_results(plans, tasks)


@pytest.mark.parametrize("forge, message", [
    ("name", "its name attribute says task_0000, tasks.json lists it as task_0001"),
    ("voxel", "its arrays do not match its ground_truth_sha256"),
    ("junk", "unreadable task file"),
    ("manifest", "is not task_NNNN with its file task_NNNN.h5"),
])
def test_a_damaged_or_misnamed_task_is_one_line_exit_2_and_nothing_written(copy, capsys, forge, message):
    tasks, plans, _ = copy
    path = tasks / "task_0001.h5"
    if forge == "name":  # one changed byte, not covered by the digests
        _set_attr(path, "name", "task_0000")
    elif forge == "voxel":  # an edited voxel, digests left
        with h5py.File(path, "a") as f:
            f["target/mask_3d"][0, 0, 0] = 1
    elif forge == "junk":
        path.write_bytes(b"\x89HDF\r\n not really")
    else:
        manifest = json.loads((tasks / "tasks.json").read_text())
        manifest["tasks"][1]["file"] = "../plans/task_0001.h5"
        (tasks / "tasks.json").write_text(json.dumps(manifest))
    out = plans.parent / "fresh"
    code, stdout, err = _plan(capsys, tasks, out)
    assert code == 2 and len(err) == 1 and message in err[0] and stdout.strip() == ""
    assert not out.exists()  # verified before anything is written


def test_recompute_refuses_missing_extra_cherry_picked_mixed_and_unreadable_plans(copy, mini):
    from dsr_bench.planning.verify import recompute_results

    tasks, plans, honest = copy
    cases = []

    def case(message, setup):
        cases.append((message, setup))

    def results(edit):
        r = json.loads(json.dumps(honest))
        edit(r)
        (plans / "results.json").write_text(json.dumps(r))

    case("results.json scores task_0003 but its plan file is missing", lambda: (plans / "task_0003.h5").unlink())
    case("task_0003.h5 is not in results.json's per_task", lambda: results(lambda r: r["per_task"].pop("task_0003")))
    case("plans of 3 tasks but not of task_0001: a partial run is a prefix", lambda: (
        (plans / "task_0001.h5").unlink(), results(lambda r: r["per_task"].pop("task_0001"))))
    case("task_0009.h5 is not a task of", lambda: shutil.copy(plans / "task_0000.h5", plans / "task_0009.h5"))
    case("task_0002.h5 was made with seed 7, task_0000.h5 with 0: not one run's plans",
         lambda: _set_attr(plans / "task_0002.h5", "seed", 7))
    case("task_0002.h5: unreadable plan file", lambda: (plans / "task_0002.h5").write_bytes(b"junk"))
    case("its start or target state is not task_0002's", lambda: _forge_states(plans / "task_0002.h5", 0))
    case("has no results.json", lambda: (plans / "results.json").unlink())
    case("not a dsr-bench planning results file", lambda: (plans / "results.json").write_text("[1, 2]"))
    for message, setup in cases:
        shutil.rmtree(plans)
        shutil.copytree(mini[1], plans)  # the honest plans again
        setup()
        with pytest.raises(UserError, match=message.replace("(", r"\(")) as e:
            recompute_results(plans, tasks)
        assert "\n" not in str(e.value), message


def _forge_states(path, step):
    with h5py.File(path, "a") as f:
        states = f["states/mask_3d"][()]
        states[step] = np.roll(states[step], 3, axis=0)
        f["states/mask_3d"].write_direct(states)


def test_an_invalid_plan_file_is_planned_again_with_one_warning(copy, capsys):
    from dsr_bench.planning.verify import recompute_results

    tasks, plans, honest = copy
    (plans / "task_0002.h5").write_bytes(b"junk")
    _forge_states(plans / "task_0003.h5", 0)
    code, out, err = _plan(capsys, tasks, plans)
    assert code == 0 and "(4/4 tasks, pinned)" in out and len(err) == 2
    assert "task_0002.h5: unreadable plan file" in err[0] and "task_0003.h5: its start or target" in err[1]
    results = json.loads((plans / "results.json").read_text())
    assert _scores(results) == _scores(honest) and recompute_results(plans, tasks) == results


def test_a_prefix_run_is_partial_pinned_and_recomputes(copy, capsys):
    from dsr_bench.planning.verify import check_results, recompute_results

    tasks, plans, honest = copy
    out = plans.parent / "prefix"
    code, stdout, err = _plan(capsys, tasks, out, "--num-tasks", "2")
    assert code == 0 and err == [] and "(2/4 tasks, pinned)" in stdout
    results = json.loads((out / "results.json").read_text())
    assert results["coverage"] == {"scored": 2, "expected": 4, "partial": True}
    assert check_results(results) == [] and recompute_results(out, tasks) == results


def _forged_results(honest):
    """(what, forged results dict) of the issue's edits of a results file."""
    import copy as copying

    def edit(what, change):
        r = copying.deepcopy(honest)
        change(r)
        return what, r

    def mean(r):
        for key in ("iou", "planning_iou"):
            r["metrics"][key] = float(np.mean([t["iou"] for _, t in sorted(r["per_task"].items())]))

    def per_task_and_mean(r):
        r["per_task"]["task_0000"]["iou"] = 0.9
        mean(r)

    return [
        edit("per-task value", lambda r: r["per_task"]["task_0000"].__setitem__("iou", 0.9)),
        edit("per-task value and its mean", per_task_and_mean),
        edit("mean", lambda r: r["metrics"].__setitem__("iou", 0.5)),
        edit("task removed", lambda r: r["per_task"].pop("task_0003")),
        edit("per_task empty", lambda r: r["per_task"].clear()),
        edit("coverage 1/4 not partial", lambda r: r.__setitem__("coverage", {"scored": 1, "expected": 4,
                                                                              "partial": False})),
        edit("checksum zeroed, pinned", lambda r: r.update(task_checksum="0" * 64, split_checksum="0" * 64)),
        edit("mini relabelled test", lambda r: r.update(task_set="plan-novel-test", split="plan-novel-test")),
        edit("iou above 1", lambda r: r["per_task"]["task_0001"].__setitem__("iou", 1.5)),
        edit("iou NaN", lambda r: r["per_task"]["task_0001"].__setitem__("iou_occupancy", float("nan"))),
        edit("iou a boolean", lambda r: r["per_task"]["task_0001"].__setitem__("start_iou", True)),
        edit("pinned false on the pin", lambda r: r.__setitem__("pinned", False)),
        edit("method renamed", lambda r: r.__setitem__("method", "dsr")),
        edit("checksum of another set", lambda r: r.update(task_set="plan-novel-test", split="plan-novel-test",
                                                            coverage={"scored": 4, "expected": 100, "partial": True})),
    ]


def test_every_forged_results_file_is_caught(copy):
    """Each forgery is a problem of `check_results`, or a field where `recompute_results` (from the plan files and
    the verified tasks) differs from it: never accepted as it is."""
    from dsr_bench.planning.verify import check_results, differences, recompute_results

    tasks, plans, honest = copy
    for what, forged in _forged_results(honest):
        problems = check_results(forged)
        (plans / "results.json").write_text(json.dumps(forged))
        try:
            differ = differences(recompute_results(plans, tasks), forged)
        except UserError as exc:
            differ = [str(exc)]
            assert "\n" not in str(exc)
        assert problems or differ, what
        assert all(isinstance(p, str) and "\n" not in p and len(p) < 100 for p in problems), what
    named = dict(_forged_results(honest))
    assert "metrics iou is not the mean of the per-task values" in check_results(named["per-task value"])
    assert check_results(named["per-task value and its mean"]) == []  # consistent in itself: only recomputing shows it
    assert "coverage partial disagrees with scored < expected" in check_results(named["coverage 1/4 not partial"])
    assert "per_task is empty" in check_results(named["per_task empty"])
    assert "coverage scored is not the number of per_task entries" in check_results(named["task removed"])
    assert "pinned is true but task_checksum is not the pin of task_set" in check_results(
        named["checksum zeroed, pinned"])
    relabelled = check_results(named["mini relabelled test"])
    assert "task_checksum is the pin of plan-novel-mini, not of plan-novel-test" in relabelled
    assert "coverage expected is not the task set's size" in relabelled
    assert any("outside [0, 1]" in p for p in check_results(named["iou above 1"]))
    assert any("outside [0, 1]" in p for p in check_results(named["iou NaN"]))
    assert "pinned is false but task_checksum is the pin of task_set" in check_results(
        named["pinned false on the pin"])
    assert "planner is not an object with the method's name and a description" in check_results(
        named["method renamed"])


@pytest.mark.parametrize("junk", [None, [], "x", {"format": "dsr-bench-plan-results"},
                                  {"per_task": [1], "metrics": "m", "coverage": None, "pinned": "yes"},
                                  {"per_task": {"task_0000": {"iou": "0.5"}}, "metrics": {"iou": None}}])
def test_check_results_reports_garbage_without_raising(junk):
    from dsr_bench.planning.verify import check_results

    problems = check_results(junk)
    assert problems and all(isinstance(p, str) and "\n" not in p for p in problems)


def _evidence(*args: str):
    """scripts/planning_evidence.py ARGS in a fresh Python: the CompletedProcess (text)."""
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).parents[1]
    return subprocess.run([sys.executable, str(root / "scripts" / "planning_evidence.py"), *args],
                          capture_output=True, text=True, cwd=root, timeout=1800)  # a hang guard only


def test_planning_evidence_recomputes_a_results_json_with_raised_scores(copy, tmp_path):
    """scripts/planning_evidence.py reads a planner's scores from its plan files, never from results.json: a
    results.json whose per-task IoUs and mean were raised is named on stderr and in the summary, and the summary's
    means and paired differences are the honest run's."""
    tasks, plans, results = copy
    (tmp_path / "P").mkdir()
    shutil.move(str(plans), tmp_path / "P" / "random")
    forged = json.loads(json.dumps(results))
    for row in forged["per_task"].values():
        row["iou"] = 1.0
    forged["metrics"]["iou"] = 1.0
    (tmp_path / "P" / "random" / "results.json").write_text(json.dumps(forged))
    out = tmp_path / "evidence.json"
    proc = _evidence(str(tmp_path / "P"), "--tasks", str(tasks), "--planners", "random", "--out", str(out))
    assert proc.returncode == 0, proc.stderr
    assert "random/results.json differs from its plan files in metrics.iou" in proc.stderr
    summary = json.loads(out.read_text())
    honest = [row["iou"] for row in results["per_task"].values()]
    assert summary["means"]["random"]["iou"] == pytest.approx(sum(honest) / len(honest), abs=1e-12)
    assert summary["means"]["random"]["iou"] < 1.0
    assert "metrics.iou" in summary["differed_from_results_json"]["P/random"]
    start = [row["start_iou"] for row in results["per_task"].values()]
    assert summary["pairs"]["random - no push"]["iou"]["mean"] == pytest.approx(
        (sum(honest) - sum(start)) / len(honest), abs=1e-12)


def test_planning_evidence_pools_two_task_sets_task_by_task(mini, tmp_path):
    """Two PLANS_DIRs pool their tasks (named i:set/task): the means are over every task of both."""
    tasks, plans, results = mini
    for d in ("A", "B"):
        (tmp_path / d).mkdir()
        shutil.copytree(plans, tmp_path / d / "random")
    out = tmp_path / "pooled.json"
    proc = _evidence(str(tmp_path / "A"), str(tmp_path / "B"), "--tasks", str(tasks), str(tasks), "--planners",
                     "random", "--out", str(out))
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(out.read_text())
    assert summary["pairs"]["random - no push"]["iou"]["n"] == 2 * len(results["per_task"])
    assert summary["means"]["random"]["iou"] == pytest.approx(results["metrics"]["iou"], abs=1e-12)


def test_planning_evidence_refuses_to_pool_one_name_run_with_different_weights(mini, tmp_path):
    """Pooling is of one planner: two directories whose runs under one name record different weights are
    refused with one line naming the planner."""
    tasks, plans, results = mini
    for d in ("A", "B"):
        (tmp_path / d).mkdir()
        shutil.copytree(plans, tmp_path / d / "random")
    other = json.loads(json.dumps(results))
    other["planner"]["weights"] = {"sha256": "0" * 64}  # self-reported: recompute_results keeps it
    (tmp_path / "B" / "random" / "results.json").write_text(json.dumps(other))
    proc = _evidence(str(tmp_path / "A"), str(tmp_path / "B"), "--tasks", str(tasks), str(tasks), "--planners",
                     "random")
    assert proc.returncode != 0
    assert "random was run with different weights" in proc.stderr.strip().splitlines()[-1]

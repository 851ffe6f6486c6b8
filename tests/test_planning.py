"""The planning track (`dsr_bench.planning`, `generators.planning`): the cost on hand-made cases, candidate
sampling, the label warp, task files (round trip, reproducibility, error paths), the learned model's batched
candidates against its forward pass, the oracle's prediction against the executed push, and a CLI run."""

import json

import h5py
import numpy as np
import pytest

from dsr_bench.constants import GRID_SHAPE, NUM_DIRECTIONS, START_FREE_RADIUS_PX
from dsr_bench.errors import UserError
from dsr_bench.planning.cost import centroids, matched_iou, object_iou, occupancy_iou, plan_cost
from dsr_bench.planning.protocol import COST_LAMBDA, MAX_BACKOFF_CELLS, UNMATCHED_POSITION_MSE


def _box(mask, label, y0, x0, z0, size=4):
    mask[y0:y0 + size, x0:x0 + size, z0:z0 + size] = label
    return mask


def _two_boxes() -> np.ndarray:
    target = np.zeros(GRID_SHAPE, np.uint8)
    _box(target, 1, 20, 20, 2)
    return _box(target, 2, 60, 60, 2)


def test_cost_of_a_known_case_with_permuted_slots():
    """Object 1 predicted exactly, object 2 shifted by 2 voxels (0.8 cm) along x, in swapped slots: the cost is
    lambda * 0.64 / 3 - 1 - 1/3 (4-voxel cubes half overlapping: IoU 32 / 96)."""
    target = _two_boxes()
    pred = np.zeros(GRID_SHAPE, np.uint8)
    _box(pred, 2, 20, 20, 2)  # slot 2 is object 1
    _box(pred, 1, 60, 62, 2)  # slot 1 is object 2, moved by 2 voxels along x
    terms = plan_cost(pred, target, num_slots=4, num_objects=2)
    assert terms.slot.tolist() == [2, 1]
    np.testing.assert_allclose(terms.iou, [1.0, 1 / 3])
    np.testing.assert_allclose(terms.position_mse, [0.0, 0.8 ** 2 / 3])
    assert terms.total == pytest.approx(COST_LAMBDA * 0.64 / 3 - 1 - 1 / 3)


def test_cost_of_an_empty_prediction_and_no_overlap_matching_by_distance():
    target = _two_boxes()
    empty = plan_cost(np.zeros(GRID_SHAPE, np.uint8), target, 4, 2)
    assert empty.total == pytest.approx(2 * COST_LAMBDA * UNMATCHED_POSITION_MSE)
    assert empty.slot.tolist() == [0, 0]
    # no overlap anywhere: each object is matched to the nearer slot (the tie-break), not arbitrarily
    pred = np.zeros(GRID_SHAPE, np.uint8)
    _box(pred, 1, 60, 70, 2)  # 10 voxels from object 2
    _box(pred, 2, 20, 30, 2)  # 10 voxels from object 1
    terms = plan_cost(pred, target, 4, 2)
    assert terms.slot.tolist() == [2, 1]
    np.testing.assert_allclose(terms.position_mse, [4.0 ** 2 / 3] * 2)
    assert centroids(target, 2)[0][0].tolist() == [21.5, 21.5, 3.5]


def test_final_scores_identity_matched_and_occupancy():
    target = _two_boxes()
    swapped = np.where(target == 1, 2, np.where(target == 2, 1, 0)).astype(np.uint8)
    assert object_iou(swapped, target, 2).tolist() == [0.0, 0.0]
    assert matched_iou(swapped, target, 2) == 1.0
    assert occupancy_iou(swapped, target) == 1.0


def test_sampling_stays_in_the_workspace_on_free_cells_and_aims_at_an_object():
    from dsr_bench.geometry import direction_vector
    from dsr_bench.planning.sampling import footprints, free_cells, sample_around_masks, sample_uniform

    mask = np.zeros(GRID_SHAPE, np.uint8)
    _box(mask, 1, 2, 2, 0, size=10)  # in a corner: many pushes would start outside the grid
    _box(mask, 3, 60, 80, 0, size=12)
    rng = np.random.default_rng(0)
    acts = sample_around_masks(mask, rng, 300)
    assert acts.shape == (300, 3) and acts.dtype == np.int64
    assert np.all((acts[:, 0] >= 0) & (acts[:, 0] < NUM_DIRECTIONS))
    assert np.all((acts[:, 1:] >= 0) & (acts[:, 1:] < 128))
    top = footprints(mask) > 0
    free = free_cells(top)
    assert free[acts[:, 1], acts[:, 2]].all()
    # the free disc is START_FREE_RADIUS_PX: a free cell has no footprint cell within that many cells
    rr, cc = np.nonzero(top)
    d2 = (acts[:, 1, None] - rr[None]) ** 2 + (acts[:, 2, None] - cc[None]) ** 2
    assert d2.min() > START_FREE_RADIUS_PX ** 2
    # every push runs into an object within MAX_BACKOFF_CELLS cells ahead
    v = direction_vector(acts[:, 0])[:, ::-1]
    ahead = np.rint(acts[:, None, 1:] + np.arange(1, MAX_BACKOFF_CELLS + 1)[None, :, None] * v[:, None, :]).astype(int)
    ahead = np.clip(ahead, 0, 127)
    assert top[ahead[..., 0], ahead[..., 1]].any(axis=1).all()
    # pushes around both objects, and the same seed gives the same candidates
    assert np.array_equal(acts, sample_around_masks(mask, np.random.default_rng(0), 300))
    uniform = sample_uniform(free, rng, 500)
    assert free[uniform[:, 1], uniform[:, 2]].all() and len(np.unique(uniform[:, 0])) == NUM_DIRECTIONS
    assert sample_around_masks(np.zeros(GRID_SHAPE, np.uint8), rng, 7).shape == (7, 3)  # nothing seen: uniform


def test_a_clear_push_sweeps_only_free_cells():
    """A push is clear when every cell of its sweep (CLEAR_SWEEP_CELLS ahead of its start) is free or off the grid."""
    from dsr_bench.constants import CLEAR_SWEEP_CELLS
    from dsr_bench.planning.sampling import clear_pushes, sample_clear

    occupied = np.zeros(GRID_SHAPE[:2], bool)
    occupied[60:72, 60:72] = True  # one object; free cells lie more than START_FREE_RADIUS_PX from it
    edge = 60 - START_FREE_RADIUS_PX - 1  # the last free column before it on row 66
    acts = np.array([
        [0, 66, edge - CLEAR_SWEEP_CELLS],      # +x (columns up): the sweep ends on the last free cell: clear
        [0, 66, edge - CLEAR_SWEEP_CELLS + 1],  # one cell later: its sweep ends within the free disc: not clear
        [4, 66, 30],                            # -x, away from the object and off the grid: clear
        [2, 20, 66],                            # +y (rows up) from row 20 straight into the object: not clear
        [6, 20, 66],                            # -y, away from it: clear
    ])
    assert clear_pushes(occupied, acts).tolist() == [True, False, True, False, True]
    rng = np.random.default_rng(3)
    keep = sample_clear(occupied, rng, 40)
    assert keep.shape == (40, 3) and clear_pushes(occupied, keep).all()
    assert np.array_equal(keep, sample_clear(occupied, np.random.default_rng(3), 40))  # seeded
    assert sample_clear(np.ones(GRID_SHAPE[:2], bool), rng, 5).shape == (0, 3)  # no room: none
    assert sample_clear(occupied, rng, 0).shape == (0, 3)


def test_an_object_push_must_beat_the_best_clear_push_by_the_margin():
    from dsr_bench.planning.runner import choose

    costs = np.array([-0.5, -0.3, -0.2, -0.25])
    clear = np.array([False, False, True, True])
    assert choose(costs, clear, 0.0) == 0 and choose(costs, clear, 0.2) == 0  # -0.5 < -0.25 - 0.2
    assert choose(costs, clear, 0.25) == 3 and choose(costs, clear, 1.0) == 3  # not by more: keep the scene
    assert choose(costs, np.zeros(4, bool), 9.0) == 0  # no clear push: the cheapest
    assert choose(costs, np.ones(4, bool), 0.0) == 0


def test_labels_move_by_their_rounded_flow_and_leave_the_grid():
    torch = pytest.importorskip("torch")  # noqa: F841 - learned.py needs torch
    from dsr_bench.planning.learned import move_labels

    mask = np.zeros(GRID_SHAPE, np.uint8)
    _box(mask, 2, 10, 10, 0)
    _box(mask, 1, 10, 124, 0)  # at the x border
    voxels = np.argwhere(mask > 0)
    flow = np.zeros((2, 3, len(voxels)), np.float32)
    flow[0, 1] = 2.6  # +3 voxels along x once rounded
    flow[1, 0] = -0.4  # rounds to no motion
    out = move_labels(mask, flow, voxels)
    assert out.shape == (2,) + GRID_SHAPE
    assert np.array_equal(out[1], mask)
    assert np.count_nonzero(out[0] == 2) == 64 and out[0][10:14, 13:17, 0:4].min() == 2
    assert np.count_nonzero(out[0] == 1) == 4 * 1 * 4  # (y, x, z): 3 of its 4 x columns moved out of the grid
    # two voxels landing on one: the later in C order stays
    two = np.zeros(GRID_SHAPE, np.uint8)
    two[5, 5, 5], two[5, 6, 5] = 3, 4
    v2 = np.argwhere(two > 0)
    onto = np.zeros((1, 3, 2), np.float32)
    onto[0, 1, 0] = 1.0  # (5, 5, 5) -> (5, 6, 5), where (5, 6, 5) stays
    moved = move_labels(two, onto, v2)[0]
    assert moved[5, 6, 5] == 4 and np.count_nonzero(moved) == 1


def test_the_sparse_cost_is_the_dense_cost_bit_for_bit():
    from dsr_bench.matching import overlap
    from dsr_bench.planning.cost import SparseLabels, TargetStats

    rng = np.random.default_rng(5)
    target = _two_boxes()
    for _ in range(5):
        pred = np.zeros(GRID_SHAPE, np.uint8)
        for label in range(1, 5):
            _box(pred, label, *rng.integers(0, 100, 2), rng.integers(0, 20), size=int(rng.integers(2, 9)))
        dense = plan_cost(pred, target, 4, 2)
        sparse = plan_cost(SparseLabels.of(pred), target, 4, 2, stats=TargetStats.of(target, 2))
        assert dense.total == sparse.total and np.array_equal(dense.slot, sparse.slot)
        assert np.array_equal(dense.position_mse, sparse.position_mse) and np.array_equal(dense.iou, sparse.iou)
        assert np.array_equal(SparseLabels.of(pred).dense(), pred)
        # against the dense overlap counts and centroids over the whole volume
        ov, pc, tc = overlap(pred, target, 4, 2), centroids(pred, 4)[0], centroids(target, 2)[0]
        for obj, slot in enumerate(sparse.slot):
            if slot:
                assert sparse.iou[obj] == ov.iou[slot - 1, obj]
                assert sparse.position_mse[obj] == (((pc[slot - 1] - tc[obj]) * 0.4) ** 2).mean()


def _synthetic_task_arrays():
    rng = np.random.default_rng(1)
    start, target = _two_boxes(), np.roll(_two_boxes(), 3, axis=1)
    poses = np.tile([0.5, 0.0, 0.02, 0, 0, 0, 1.0], (2, 1))
    cube_v = np.array([[x, y, z] for x in (-.01, .01) for y in (-.01, .01) for z in (-.01, .01)], float)
    return {"start/object_poses": poses, "start/mask_3d": start, "target/object_poses": poses + 0.01,
            "target/mask_3d": target, "reference/action": np.array([[0, 5, 5], [1, 6, 6], [2, 7, 7]], np.int64),
            "start/tsdf": rng.uniform(-1, 1, GRID_SHAPE).astype(np.float32),
            "start/heightmap": np.zeros(GRID_SHAPE[:2], np.float32),
            "objects/0/part_0/vertices": cube_v, "objects/0/part_0/faces": np.zeros((12, 3), np.int64),
            "objects/1/part_0/vertices": cube_v, "objects/1/part_0/faces": np.zeros((12, 3), np.int64)}


def test_task_file_round_trip_and_error_paths(tmp_path):
    from dsr_bench.planning.tasks import read_task, write_task

    arrays = _synthetic_task_arrays()
    objects = [{"color": [1, 0, 0], "mass": 0.05}, {"color": [0, 1, 0], "mass": 0.05}]
    path = write_task(tmp_path / "task_0000.h5", arrays, {"name": "task_0000", "seed": 5, "num_objects": 2,
                                                          "objects": objects})
    task = read_task(path)
    assert task.num_objects == 2 and task.seed == 5 and len(task.parts) == 2
    assert np.array_equal(task.target_mask, arrays["target/mask_3d"])
    with pytest.raises(UserError, match="task file not found: .*missing.h5; generate the tasks with"):
        read_task(tmp_path / "missing.h5")
    (tmp_path / "junk.h5").write_bytes(b"not hdf5")
    with pytest.raises(UserError, match="junk.h5: unreadable task file .*regenerate it with `dsr-bench generate-plan"):
        read_task(tmp_path / "junk.h5")
    with h5py.File(path, "a") as f:  # an edited voxel: the digest no longer matches
        f["target/mask_3d"][0, 0, 0] = 1
    with pytest.raises(UserError, match="do not match its ground_truth_sha256") as err:
        read_task(path)
    assert "\n" not in str(err.value) and str(path) in str(err.value)
    with h5py.File(path, "a") as f:
        del f["start/tsdf"]
    with pytest.raises(UserError, match="missing arrays start/tsdf"):
        read_task(path)


def test_errors_of_the_commands_are_one_line_with_exit_2(tmp_path, capsys):
    pytest.importorskip("pybullet")
    from dsr_bench.cli import main

    assert main(["plan", "--model", "random", "--tasks", str(tmp_path / "nowhere"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: task directory not found") and "generate-plan-tasks" in err and "\n" not in err
    assert main(["plan", "--model", "nosuch", "--tasks", str(tmp_path), "--out", str(tmp_path / "o")]) == 2
    assert "choose one of random, oracle" in capsys.readouterr().err
    assert main(["plan", "--model", "se3net", "--tasks", str(tmp_path), "--out", str(tmp_path / "o")]) == 2
    assert "predict image flow, not the 3D masks" in capsys.readouterr().err
    for model, words in (("3dflow,random", "'random' is not a planner"), ("3dflow,3dflow", "named twice"),
                         ("3dflow,gtwarp", "gtwarp needs ground-truth flow"), ("3dflow,se3net", "predict image"),
                         ("random ", "'random ' is not a planner"), ("3dflow, single", "' single' is not a planner")):
        assert main(["plan", "--model", model, "--tasks", str(tmp_path), "--out", str(tmp_path / "o")]) == 2
        err = capsys.readouterr().err
        assert words in err and err.count("\n") == 1, model
    assert main(["plan", "--model", "3dflow,single", "--checkpoint", str(tmp_path / "c.pt"), "--tasks", str(tmp_path),
                 "--out", str(tmp_path / "o")]) == 2
    assert "an ensemble (--model 3dflow,single) plans with each model's shipped weights" in capsys.readouterr().err
    assert main(["generate-plan-tasks", "--tasks", "nosuch", "--out", str(tmp_path)]) == 2
    assert "unknown task set 'nosuch'" in capsys.readouterr().err


@pytest.fixture(scope="module")
def one_task(tmp_path_factory):
    pytest.importorskip("pybullet")
    from dsr_bench.cli import main

    out = tmp_path_factory.mktemp("plan") / "tasks"
    assert main(["generate-plan-tasks", "--tasks", "plan-novel-mini", "--num-tasks", "1", "--out", str(out)]) == 0
    return out


def test_tasks_are_reproducible_from_their_seed(one_task):
    """The same seed gives the same task digests (and the manifest's checksum); another seed another task."""
    from dsr_bench.dataset.splits import sequence_seed
    from dsr_bench.planning.tasks import PINS_FILE, TASK_SETS, load_manifest, read_task, task_digests
    from dsr_bench.generators.objects import get_object_set
    from dsr_bench.generators.planning import make_task

    task = read_task(one_task / "task_0000.h5")
    spec = TASK_SETS["plan-novel-mini"]
    assert task.seed == sequence_seed(spec.base_seed, 0)
    objects = get_object_set("procedural-novel")
    again, attrs = make_task(objects, task.seed, "task_0000", 3, "procedural-novel", 4)
    assert task_digests(again, attrs["objects"])["ground_truth_sha256"] == task.ground_truth_sha256
    assert task_digests(again, attrs["objects"])["observations_sha256"] == task.attrs["observations_sha256"]
    other, other_attrs = make_task(objects, task.seed + 1, "task_0000", 3, "procedural-novel", 4)
    assert task_digests(other, other_attrs["objects"])["ground_truth_sha256"] != task.ground_truth_sha256
    pinned = json.loads(PINS_FILE.read_text())["task_sets"]["plan-novel-mini"]["tasks"]["task_0000"]
    assert pinned["ground_truth"] == task.ground_truth_sha256  # the pin made on the maintainers' machine
    manifest = load_manifest(one_task)
    assert manifest["tasks"][0]["ground_truth_sha256"] == task.ground_truth_sha256 and len(manifest["checksum"]) == 64


def test_random_planner_from_the_cli_end_to_end(one_task, tmp_path, capsys):
    from dsr_bench.cli import main
    from dsr_bench.planning.plans import read_plan
    from dsr_bench.leaderboard.board import NO_PUSH, planning_rows

    out = tmp_path / "random"
    assert main(["plan", "--model", "random", "--tasks", str(one_task), "--out", str(out)]) == 0
    assert "random on plan-novel-mini (1/4 tasks" in capsys.readouterr().out
    results = json.loads((out / "results.json").read_text())
    assert results["format"] == "dsr-bench-plan-results" and results["coverage"] == {"scored": 1, "expected": 4,
                                                                                     "partial": True}
    assert results["command"].startswith("dsr-bench plan --model random --tasks")
    per_task = results["per_task"]["task_0000"]
    assert 0 <= per_task["iou"] <= 1 and results["metrics"]["iou"] == per_task["iou"]
    arrays, attrs = read_plan(out / "task_0000.h5")
    assert arrays["actions"].shape == (3, 3) and arrays["states/mask_3d"].shape == (4,) + GRID_SHAPE
    assert attrs["iou"] == per_task["iou"] and np.isnan(arrays["costs"]).all()
    try:
        import rerun  # noqa: F401
    except ImportError:
        pass
    else:  # a plan file opens in the viewer: target, candidates, chosen push, states
        assert main(["view", str(out / "task_0000.h5"), "--save", str(tmp_path / "plan.rrd")]) == 0
        assert (tmp_path / "plan.rrd").stat().st_size > 0
    rows = planning_rows([out / "results.json"])
    assert rows[0]["method"] == "random (planning)" and rows[0]["planning_iou"] == per_task["iou"]
    no_push = [r for r in rows if r["method"] == NO_PUSH]
    assert len(no_push) == 1 and no_push[0]["planning_iou"] == per_task["start_iou"]  # the reference row
    assert {r["planning_iou"] for r in rows[1:] if r["method"] != NO_PUSH} == {0.72, 0.31, 0.32}  # the paper's


def test_oracle_prediction_is_the_executed_push(one_task):
    """The oracle's next state of the chosen candidate is, bit for bit, the state the executed push leaves."""
    from dsr_bench.planning.planners import make_planner
    from dsr_bench.planning.runner import run_plan
    from dsr_bench.planning.tasks import read_task
    from dsr_bench.generators.planning import SimEnvironment

    task = read_task(one_task / "task_0000.h5")
    env = SimEnvironment()
    try:
        record = run_plan(task, make_planner("oracle", (env.current_mask, env.simulate)), env, candidates=3, steps=2)
    finally:
        env.close()
    assert np.array_equal(record.states[0].mask_3d, task.start_mask)
    for k in range(2):
        assert np.array_equal(record.predicted[k], record.states[k + 1].mask_3d)
        assert record.costs[k][record.chosen[k]] == record.costs[k].min()


def test_a_learned_plan_keeps_the_scene_unless_a_push_beats_the_margin(one_task):
    """With an unreachable margin the DSR-Net planner executes only clear pushes, and the scene stays as it was
    (objects settle by a few voxels when a push's world is rebuilt); with margin 0 it executes the cheapest."""
    pytest.importorskip("torch")
    from dsr_bench.planning.planners import make_planner
    from dsr_bench.planning.runner import run_plan
    from dsr_bench.planning.tasks import read_task
    from dsr_bench.generators.planning import SimEnvironment

    task = read_task(one_task / "task_0000.h5")
    planner = make_planner("dsr")
    env = SimEnvironment()
    try:
        kept = run_plan(task, planner, env, candidates=14, steps=2, margin=1e9, clear=10)
        pushed = run_plan(task, planner, env, candidates=14, steps=1, margin=0.0, clear=10)
    finally:
        env.close()
    for k in range(2):
        assert kept.clear[k].sum() == 10 and kept.clear[k][kept.chosen[k]]
    assert matched_iou(kept.states[-1].mask_3d, task.start_mask, task.num_objects) > 0.97
    assert pushed.costs[0][pushed.chosen[0]] == pushed.costs[0].min()


def test_replaying_the_reference_pushes_reaches_the_target_exactly(one_task):
    """The planning world is the generator's: each push starts from a world built afresh at the rest poses
    (`PushWorld.restart`), so the task's own reference pushes, executed from its start, leave the objects at its
    target poses bit for bit (and a push of another cell does not)."""
    from dsr_bench.planning.tasks import read_task
    from dsr_bench.generators.planning import SimEnvironment

    task = read_task(one_task / "task_0000.h5")
    env = SimEnvironment()
    try:
        env.reset(task)
        for action in task.arrays["reference/action"]:
            env.step(action)
        assert np.array_equal(env.world.poses(), task.arrays["target/object_poses"])
        assert np.array_equal(env.current_mask(), task.target_mask)
        env.reset(task)
        first = task.arrays["reference/action"][0]
        moved = env.simulate(np.array([first, [(first[0] + 4) % 8, first[1], first[2]]]))
        assert not np.array_equal(moved[0], moved[1])
        assert np.array_equal(env.world.rest_poses, task.arrays["start/object_poses"])  # simulate puts it back
        np.testing.assert_allclose(env.world.poses(), task.arrays["start/object_poses"], atol=1e-12)
    finally:
        env.close()


def test_batched_candidates_match_the_networks_forward_pass():
    torch = pytest.importorskip("torch")
    from dsr_bench.models import coarse
    from dsr_bench.models.data import action_map
    from dsr_bench.models.labels import slot_labels
    from dsr_bench.models.predictors import load_predictor, shipped_weights
    from dsr_bench.planning.learned import BatchedModel

    if shipped_weights("dsr") is None:
        pytest.skip("no shipped dsr weights")
    predictor = load_predictor("dsr")
    model = BatchedModel(predictor)
    tsdf = np.ones(GRID_SHAPE, np.float32)
    tsdf[40:60, 40:60, :8] = -0.5
    labels = model.observe(tsdf)
    actions = np.array([[0, 50, 30], [3, 20, 90], [6, 64, 64]], np.int64)
    motion = model.motion(actions)
    net = predictor.model
    with torch.no_grad():
        for i, a in enumerate(actions):
            x = torch.from_numpy(coarse.pool_tsdf(tsdf)).unsqueeze(0)
            out = net(x, action_map(coarse.coarse_action(a[None]), net.config.grid[:2]), net.initial_state(1, "cpu"))
            torch.testing.assert_close(motion[i: i + 1], out["motion"], rtol=1e-4, atol=1e-4)
    assert np.array_equal(labels, coarse.unpool_mask(slot_labels(out["mask"])[0].numpy()))
    assert model.predict(actions).shape == (3,) + GRID_SHAPE


def test_an_ensemble_moves_the_first_models_objects_by_the_mean_motion():
    """`3dflow,single,dsr`: the first model's labels, each voxel moved by the mean of the three models' flows at it
    (checked against moving them by hand), each model carrying its own history; one member twice is that member."""
    pytest.importorskip("torch")
    from dsr_bench.models.predictors import load_predictor, shipped_weights
    from dsr_bench.planning.learned import BatchedModel, MotionEnsemble, moved_labels
    from dsr_bench.planning.planners import make_planner

    if any(shipped_weights(m) is None for m in ("3dflow", "single", "dsr")):
        pytest.skip("no shipped weights")
    tsdf = np.ones(GRID_SHAPE, np.float32)
    tsdf[40:60, 40:60, :8] = -0.5
    tsdf[80:96, 70:90, :6] = -0.5
    actions = np.array([[0, 50, 30], [3, 20, 90], [6, 64, 64]], np.int64)
    planner = make_planner("3dflow,single,dsr", masks="observed")
    assert planner.name == "mean(3dflow-cpu, single-cpu, dsr-cpu)+observed" and len(planner.weights) == 3
    alone = [BatchedModel(load_predictor(m), masks) for m, masks in (("3dflow", "observed"), ("single", "model"),
                                                                     ("dsr", "model"))]
    for step in range(2):  # the second step runs on the histories the executed push left
        labels = planner.observe(tsdf)
        for model in alone:
            model.observe(tsdf)
        assert np.array_equal(labels, alone[0]._labels)
        v = np.argwhere(labels > 0)
        flows = [model.motion_at(actions, v) for model in alone]
        assert max(float(np.abs(a - b).max()) for a, b in zip(flows, flows[1:])) > 0.1  # the members differ
        expected = moved_labels(labels, (flows[0] + flows[1] + flows[2]) / np.float32(3), v)
        got = planner.predict_labels(actions)
        assert all(np.array_equal(a.dense(), b.dense()) for a, b in zip(got, expected)), step
        planner.executed(actions[step])
        for model in alone:
            model.executed(actions[step])
    twice = MotionEnsemble([BatchedModel(load_predictor("3dflow")), BatchedModel(load_predictor("3dflow"))])
    one = BatchedModel(load_predictor("3dflow"))
    twice.observe(tsdf), one.observe(tsdf)
    assert all(np.array_equal(a.dense(), b.dense()) for a, b in zip(twice.predict_labels(actions),
                                                                     one.predict_labels(actions)))


def test_every_task_set_is_pinned_whole_and_seeded_apart_from_every_split():
    """Each named task set has a pin of exactly its tasks (task_0000.. in order) and a checksum, and its base
    seed is its own: no other task set's or benchmark split's, so no task repeats a scene of another set or of a
    training or test sequence of the same objects."""
    from dsr_bench.dataset.splits import SPLITS
    from dsr_bench.planning.tasks import PINS_FILE, TASK_SETS, task_name

    pins = json.loads(PINS_FILE.read_text())["task_sets"]
    for name, spec in TASK_SETS.items():
        assert name in pins, f"{name} is not pinned (dsr-bench generate-plan-tasks --tasks {name} --pin)"
        assert list(pins[name]["tasks"]) == [task_name(i) for i in range(spec.num_tasks)], name
        assert len(pins[name]["checksum"]) == 64
    seeds = [s.base_seed for s in TASK_SETS.values()]
    assert len(set(seeds)) == len(seeds)
    assert not set(seeds) & {s.base_seed for s in SPLITS.values()}

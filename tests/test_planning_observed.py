"""The planner's objects of the current state from the TSDF's geometry (dsr_bench.planning.observed), and a learned
planner that uses them in place of its network's masks."""

import numpy as np
import pytest

from dsr_bench.constants import FOOTPRINT_MIN_Z, GRID_SHAPE
from dsr_bench.planning.observed import MIN_OBSERVED_VOXELS, observed_objects, observed_occupancy, slots_for


def _tsdf_with_tops(*tops) -> np.ndarray:
    """A TSDF that has seen nothing but a surface band at height z over each box (y0, y1, x0, x1, z)."""
    tsdf = np.ones(GRID_SHAPE, np.float32)
    tsdf[:, :, 0] = -0.5  # the table's band: below FOOTPRINT_MIN_Z, never an object
    for y0, y1, x0, x1, z in tops:
        tsdf[y0:y1, x0:x1, z] = -0.5
        tsdf[y0:y1, x0:x1, z + 1] = 0.5  # in front of the surface: free
    return tsdf


def test_occupancy_fills_each_seen_column_from_the_table_to_its_top():
    occ = observed_occupancy(_tsdf_with_tops((10, 20, 10, 20, 8), (50, 52, 50, 52, FOOTPRINT_MIN_Z - 1)))
    assert occ[10:20, 10:20, :9].all() and not occ[10:20, 10:20, 9:].any()
    assert np.count_nonzero(occ) == 10 * 10 * 9  # the low band and the table's are not objects


def test_objects_are_the_largest_components_by_size():
    tsdf = _tsdf_with_tops((10, 20, 10, 20, 8), (60, 64, 60, 64, 12), (100, 102, 100, 102, 3), (30, 40, 90, 95, 5))
    objects = observed_objects(tsdf, 5)
    sizes = [np.count_nonzero(objects == k) for k in (1, 2, 3)]
    assert sizes == [900, 300, 208] and objects.max() == 3  # 2 x 2 x 4 = 16 < MIN_OBSERVED_VOXELS: dropped
    assert 16 < MIN_OBSERVED_VOXELS
    assert objects[15, 15, 0] == 1 and objects[35, 92, 0] == 2 and objects[62, 62, 12] == 3
    assert observed_objects(tsdf, 2).max() == 2  # the largest two
    touching = observed_objects(_tsdf_with_tops((10, 20, 10, 20, 8), (10, 20, 20, 30, 4)), 5)
    assert touching.max() == 1  # touching objects are one component (a limit, documented)


def test_objects_take_the_slot_they_share_most_voxels_with():
    objects = np.zeros(GRID_SHAPE, np.uint8)
    objects[0:10, 0:10, 0:4], objects[50:60, 50:60, 0:4], objects[90:95, 90:95, 0:4] = 1, 2, 3
    slots = np.zeros(GRID_SHAPE, np.uint8)
    slots[0:10, 0:6, 0:4] = 4  # most of object 1
    slots[0:10, 6:10, 0:4] = 2
    slots[50:60, 50:60, 0:4] = 2  # all of object 2: slot 2 goes to object 2, object 1 keeps slot 4
    out = slots_for(objects, slots, 4)
    assert out[5, 2, 0] == 4 and out[5, 8, 0] == 4 and out[55, 55, 0] == 2
    assert out[92, 92, 0] in (1, 3) and len(np.unique(out)) == 4  # object 3, sharing nothing, takes a free slot
    assert slots_for(np.zeros(GRID_SHAPE, np.uint8), slots, 4).max() == 0


def test_a_learned_planner_moves_the_observed_objects(tmp_path):
    """DSR-Net with masks='observed' on a real task: its labels are the observed objects, each voxel moved by the
    network's motion at it, and the CLI records the choice in the plan files and results."""
    pytest.importorskip("torch")
    pytest.importorskip("pybullet")
    import json

    from dsr_bench.cli import main
    from dsr_bench.planning.planners import make_planner
    from dsr_bench.planning.plans import read_plan
    from dsr_bench.planning.tasks import read_task
    import h5py

    from dsr_bench.errors import UserError
    from dsr_bench.planning.verify import recompute_results

    tasks = tmp_path / "tasks"
    assert main(["generate-plan-tasks", "--tasks", "plan-novel-mini", "--num-tasks", "1", "--out", str(tasks)]) == 0
    task = read_task(tasks / "task_0000.h5")
    planner = make_planner("dsr", masks="observed")
    labels = planner.observe(task.arrays["start/tsdf"])
    objects = observed_objects(task.arrays["start/tsdf"], planner.num_slots)
    assert np.array_equal(labels > 0, objects > 0) and labels.max() <= planner.num_slots
    assert planner.name.endswith("+observed")
    out = tmp_path / "plans"
    assert main(["plan", "--model", "dsr", "--masks", "observed", "--tasks", str(tasks), "--out", str(out),
                 "--candidates", "12"]) == 0
    results = json.loads((out / "results.json").read_text())
    assert results["parameters"]["masks"] == "observed" and results["method"].startswith("dsr-cpu+observed")
    assert "--masks observed" in results["command"]
    arrays, attrs = read_plan(out / "task_0000.h5")
    assert attrs["masks"] == "observed" and arrays["clear"].shape == (3, 12)
    # a learned plan replays: its states, its candidates around its masks, its choice and the chosen push's cost
    assert recompute_results(out, tasks) == results
    with h5py.File(out / "task_0000.h5", "a") as f:  # the chosen push's predicted masks edited: its cost is not theirs
        predicted = f["predicted"][()]
        predicted[1] = 0
        f["predicted"].write_direct(predicted)
    with pytest.raises(UserError, match="task_0000.h5: step 1: the chosen push's cost is not the cost of its stored "
                                        "predicted masks"):
        recompute_results(out, tasks)
    assert main(["plan", "--model", "random", "--masks", "observed", "--tasks", str(tasks), "--out", str(out)]) == 2

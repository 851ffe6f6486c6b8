"""A volume's flow read at world points (`geometry.projection.flow_at_points`): how a 3D prediction (DSR-Net) is
scored on the 2D track. Known answers: a labelled block of constant motion, the trilinear weights, and the ground
truth's 3D flow projected onto a sequence's front camera agreeing with its stored 2D ground truth."""

import numpy as np
import pytest

from dsr_bench.constants import GRID_SHAPE, VOXEL_SIZE
from dsr_bench.geometry import flow_at_points, voxel_to_world
from dsr_bench.scoring.metrics import motion_2d_error

#: a block of voxels (iy, ix, iz) ranges, away from the grid's diagonal so that swapping x and y misses it
BLOCK = (slice(10, 20), slice(60, 70), slice(5, 10))
BLOCK_MOTION = np.array([1.5, -2.0, 0.5])  # voxels (dy, dx, dz)
OUTSIDE_MOTION = 7.0  # the motion of every unlabelled voxel: must never leak in


def _block() -> tuple[np.ndarray, np.ndarray]:
    motion = np.full((3,) + GRID_SHAPE, OUTSIDE_MOTION, np.float32)
    mask = np.zeros(GRID_SHAPE, np.uint8)
    mask[BLOCK] = 2
    motion[(slice(None),) + BLOCK] = BLOCK_MOTION[:, None, None, None]
    return motion, mask


def test_points_in_a_labelled_block_get_its_motion_in_metres_and_others_zero():
    motion, mask = _block()
    rng = np.random.default_rng(0)
    lo, hi = np.array([s.start for s in BLOCK]), np.array([s.stop - 1 for s in BLOCK])
    inside = voxel_to_world(rng.uniform(lo, hi + 0.999, size=(6, 5, 3)))  # up to just below the next voxel
    flow = flow_at_points(motion, mask, inside)
    assert flow.shape == (6, 5, 3) and flow.dtype == np.float32
    np.testing.assert_allclose(flow, np.broadcast_to(BLOCK_MOTION * VOXEL_SIZE, flow.shape), rtol=1e-6, atol=1e-9)
    swapped = inside[..., [1, 0, 2]] + np.array([0.0, 0.5, 0.0])  # x and y exchanged (re-centred): misses the block
    far = voxel_to_world(np.array([[[60.0, 15.0, 7.0]], [[100.0, 100.0, 30.0]]]))  # unlabelled voxels only
    points = np.concatenate([far, [[[np.nan, np.nan, np.nan]]], [[[2.0, 0.0, 0.05]]],
                             voxel_to_world(np.array([[[-0.5, 64.0, 6.0]]]))], axis=0)
    assert not np.any(flow_at_points(motion, mask, points))  # unlabelled, NaN, outside the grid, on its edge
    assert not np.any(flow_at_points(motion, mask, swapped[:1]))


def test_trilinear_weights_over_the_labelled_voxels_only():
    motion = np.zeros((3,) + GRID_SHAPE, np.float32)
    mask = np.zeros(GRID_SHAPE, np.uint8)
    a, b = np.array([4.0, 0.0, -1.0]), np.array([0.0, 8.0, 3.0])
    motion[:, 30, 40, 10], motion[:, 30, 41, 10] = a, b  # two neighbours along x (the volume's second axis)
    motion[:, 31, 40, 10] = 100.0  # a neighbour along y, not labelled: ignored
    mask[30, 40, 10] = mask[30, 41, 10] = 1
    fractions = np.array([0.0, 0.25, 0.5, 0.9])
    voxels = np.stack([np.full(4, 30.3), 40 + fractions, np.full(4, 10.6)], axis=1)  # off the voxels in y and z
    flow = flow_at_points(motion, mask, voxel_to_world(voxels)[None])[0]
    expected = ((1 - fractions)[:, None] * a + fractions[:, None] * b) * VOXEL_SIZE
    np.testing.assert_allclose(flow, expected, rtol=1e-5, atol=1e-9)


def test_bad_shapes_are_refused():
    motion, mask = _block()
    with pytest.raises(ValueError, match="motion must be"):
        flow_at_points(motion[:, :64], mask, np.zeros((2, 2, 3)))
    with pytest.raises(ValueError, match="mask must be"):
        flow_at_points(motion, mask[None], np.zeros((2, 2, 3)))
    with pytest.raises(ValueError, match="points must be"):
        flow_at_points(motion, mask, np.zeros((2, 2, 2)))


def _projection_errors(flow3d, mask3d, points, flow2d, mask2d) -> dict[str, float]:
    """2D flow MSE (cm²) over the object pixels of the projected ground truth, of zero flow and of two mistakes;
    "projected median": the median over object pixels of the projected ground truth's squared error (cm²)."""
    errors = {"projected": [], "zero": [], "x and y swapped": [], "in voxels, not metres": []}
    per_pixel = []
    for t in range(len(flow3d)):
        projected = flow_at_points(flow3d[t], mask3d[t], points[t])
        if not (mask2d[t] > 0).any():
            continue
        per_pixel.append(np.sum((projected - flow2d[t]) ** 2, axis=-1)[mask2d[t] > 0] * 1e4)
        for key, pred in (("projected", projected), ("zero", np.zeros_like(projected)),
                          ("x and y swapped", flow_at_points(flow3d[t][[1, 0, 2]], mask3d[t], points[t])),
                          ("in voxels, not metres", projected / VOXEL_SIZE)):
            errors[key].append(motion_2d_error(pred, flow2d[t], mask2d[t]))
    return {**{k: float(np.mean(v)) for k, v in errors.items()},
            "projected median": float(np.median(np.concatenate(per_pixel)))}


def _check_agreement(errors: dict[str, float], bound: float, statistic: str = "projected") -> None:
    assert errors["zero"] > 1.0, errors  # the objects move: zero flow is far off
    assert errors[statistic] < bound, errors
    for mistake in ("x and y swapped", "in voxels, not metres"):
        assert errors[mistake] > 10 * errors["projected"] and errors[mistake] > 0.5 * errors["zero"], errors


def test_projected_ground_truth_agrees_with_the_2d_ground_truth_synthetic():
    """Boxes pushed 3 cm and turned 0.2 rad (`dsr_bench.testing`): the 3D ground truth read at the front camera's
    points is the stored 2D ground truth to well under a voxel (measured: 0.0007 cm² against 4.6 for zero flow)."""
    from dsr_bench.testing import synthetic_arrays

    arrays, _, _ = synthetic_arrays(num_steps=2, num_objects=2, seed=0)
    errors = _projection_errors(arrays["scene_flow_3d"], arrays["mask_3d"], arrays["cameras/front/points"],
                                arrays["cameras/front/scene_flow_2d"], arrays["cameras/front/mask"])
    _check_agreement(errors, bound=0.01)  # 0.01 cm²: a 1 mm error on every object pixel


def test_projected_ground_truth_agrees_with_the_2d_ground_truth_generated(generated_dataset):
    """The same on the real generator's sequence (pybullet scenes), on the median object pixel: where two objects
    touch, the trilinear read at a pixel of one takes in voxels of the other (12 pixels of this fixture's last step,
    after a push left two objects in contact, up to 37 cm²: mean 0.04 cm², median 3e-11, zero flow 38). Pixels of
    objects pushed off the grid have no labelled voxel either (none in this fixture; 5% of the object pixels of
    cpu-novel-test, which score 0.13 cm² this way)."""
    from dsr_bench.dataset.sequence import SequenceReader

    with SequenceReader(generated_dataset / "seq_0000.h5") as seq:
        steps = seq.num_steps
        errors = _projection_errors(seq.read("scene_flow_3d"), seq.read("mask_3d", slice(0, steps)),
                                    seq.read("cameras/front/points", slice(0, steps)),
                                    seq.read("cameras/front/scene_flow_2d"),
                                    seq.read("cameras/front/mask", slice(0, steps)))
    _check_agreement(errors, bound=1e-4, statistic="projected median")


def test_dsr_predictor_projects_its_flow_onto_the_front_camera(tmp_path):
    """`ModelPredictor.predict_sequence` adds motion_2d: its own motion and mask (on the benchmark's grid) read at
    the front camera's points; `predict` writes it and `evaluate` scores it on the 2D track too."""
    pytest.importorskip("torch")
    import json

    from dsr_bench.cli import main
    from dsr_bench.dataset.sequence import SequenceReader
    from dsr_bench.models.predictors import load_predictor, shipped_weights
    from dsr_bench.testing import write_synthetic_dataset

    if shipped_weights("dsr") is None:
        pytest.skip("no shipped CPU-track weights for dsr")
    data = write_synthetic_dataset(tmp_path / "data", num_sequences=1, num_steps=2)
    predictor = load_predictor("dsr")
    with SequenceReader(data / "seq_0000.h5") as seq:
        out = predictor.predict_sequence(seq)
        points = seq.read("cameras/front/points", slice(0, seq.num_steps))
    assert out["motion_2d"].shape == (2, 240, 320, 3) and out["motion_2d"].dtype == np.float32
    for t in range(2):
        np.testing.assert_array_equal(out["motion_2d"][t], flow_at_points(out["motion"][t], out["mask"][t], points[t]))
    assert np.any(out["motion_2d"])  # the model predicts some motion on the objects it sees
    pred = tmp_path / "pred"
    assert main(["predict", "--model", "dsr", "--data", str(data), "--out", str(pred)]) == 0
    assert main(["evaluate", str(pred), "--out", str(tmp_path / "r.json")]) == 0
    metrics = json.loads((tmp_path / "r.json").read_text())["metrics"]
    assert metrics["motion_2d"] > 0 and metrics["motion_visible"] > 0

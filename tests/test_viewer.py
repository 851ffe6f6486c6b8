"""`dsr-bench view --save`: the recording holds the entities, timelines and values we log, read
back with rerun's own tools (`rerun rrd verify`, `rerun rrd print`, the SDK's `rerun.chunk.RrdReader`)."""

import shutil
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

import h5py
import numpy as np
import pytest

pytest.importorskip("rerun")

from dsr_bench.cli import main  # noqa: E402
from dsr_bench.constants import VOXEL_SIZE  # noqa: E402
from dsr_bench.geometry import voxel_to_world, world_to_voxel  # noqa: E402
from dsr_bench.scoring.predictions import write_predictions  # noqa: E402
from dsr_bench.dataset.sequence import SequenceReader  # noqa: E402
from dsr_bench.testing import write_synthetic_sequence  # noqa: E402
from dsr_bench.viewer import (COMPARE_COLORS, EYE_POSITION, EYE_TARGET, GT_FLOW_COLOR, MAX_ARROWS,  # noqa: E402
                              PRED_FLOW_COLOR, UNMATCHED, colored_cloud, compare_voxels, match_slots)

STEPS, OBJECTS = 3, 2


def _rerun() -> str:
    local = Path(sys.executable).parent / "rerun"
    found = str(local) if local.exists() else shutil.which("rerun")
    if found is None:
        pytest.skip("the rerun command-line tool is not installed")
    return found


def _array(scalar) -> np.ndarray:
    """A logged component batch (pyarrow list scalar) as a flat numpy array."""
    import pyarrow as pa

    values = scalar.values
    if pa.types.is_struct(values.type):  # a tensor (bar chart): its data buffer
        return np.asarray([row["buffer"] for row in values.to_pylist()]).reshape(-1)
    while hasattr(values, "flatten"):
        values = values.flatten()
    return values.to_numpy(zero_copy_only=False)


class Recording:
    """The rows of an .rrd per (entity, component): [(step or None if static, pyarrow value)]."""

    def __init__(self, path: Path):
        from rerun.chunk import RrdReader

        reader = RrdReader(path)
        self.rows: dict[tuple[str, str], list] = defaultdict(list)
        self.timelines: set[str] = set()
        for chunk in reader.stream():
            batch = chunk.to_record_batch()
            self.timelines |= set(chunk.timeline_names)
            steps = batch.column("step").to_pylist() if "step" in batch.schema.names else [None] * batch.num_rows
            for name in batch.schema.names:
                if ":" in name:
                    col = batch.column(name)
                    self.rows[chunk.entity_path, name] += [(steps[i], col[i]) for i in range(batch.num_rows)]
        for rows in self.rows.values():
            rows.sort(key=lambda r: -1 if r[0] is None else r[0])
        self.blueprint_entities: set[str] = set()
        self.blueprint_rows: dict[str, list] = defaultdict(list)  # component -> values over all views
        for store in reader.blueprints():
            for chunk in reader.stream(store=store):
                self.blueprint_entities.add(chunk.entity_path)
                batch = chunk.to_record_batch()
                for name in batch.schema.names:
                    if ":" in name:
                        self.blueprint_rows[name] += batch.column(name).to_pylist()

    def steps(self, entity: str, component: str) -> list:
        return [s for s, _ in self.rows[entity, component]]

    def values(self, entity: str, component: str, width: int | None = None) -> list[np.ndarray]:
        out = [_array(v) for _, v in self.rows[entity, component]]
        return [v.reshape(-1, width) if width else v for v in out]


def _predictions(seq_path: Path, pred_dir: Path) -> dict:
    """Predictions with permuted slot ids, one extra wrong voxel block per step and flow = GT + 1 voxel in dy."""
    with SequenceReader(seq_path) as seq:
        gt = seq.read("mask_3d")[:STEPS]
        flow = seq.read("scene_flow_3d")
    perm = np.array([0, 3, 1], np.uint8)  # object 1 -> slot 3, object 2 -> slot 1, slot 2 stays empty
    mask = perm[gt]
    mask[:, :4, :4, :4] = 2  # an unmatched slot in a corner no object occupies
    for t in range(STEPS):  # 5 voxels of object 1 given object 2's slot: occupied on both sides, yet wrong
        idx = np.argwhere(gt[t] == 1)[:5]
        mask[t][tuple(idx.T)] = 1
    motion = flow.copy()
    motion[:, 0] += 1.0
    write_predictions(pred_dir / f"{seq_path.stem}.h5", mask, motion, num_slots=3)
    return {"gt": gt, "mask": mask}


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    root = tmp_path_factory.mktemp("viewer")
    seq = write_synthetic_sequence(root / "data" / "seq_0007.h5", STEPS, OBJECTS, seed=5)
    pred = _predictions(seq, root / "pred")
    rrd = root / "out" / "seq_0007.rrd"
    assert main(["view", "seq_0007", "--data", str(root / "data"), "--predictions", str(root / "pred"),
                 "--save", str(rrd)]) == 0
    return {"seq": seq, "rrd": rrd, "rec": Recording(rrd), "pred": pred, "pred_dir": root / "pred"}


def test_recording_verifies_with_rerun_tools(synthetic):
    result = subprocess.run([_rerun(), "rrd", "verify", str(synthetic["rrd"])], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    printed = subprocess.run([_rerun(), "rrd", "print", str(synthetic["rrd"])], capture_output=True, text=True,
                             check=True).stdout
    assert "/world/gt/mask" in printed and "/world/pred/compare/only_predicted" in printed
    assert list(synthetic["rrd"].parent.iterdir()) == [synthetic["rrd"]]  # no temporary file left behind


def test_timelines_and_blueprint(synthetic):
    rec = synthetic["rec"]
    assert {"step", "observation"} <= rec.timelines
    assert "/viewport" in rec.blueprint_entities  # the layout travels with the recording
    # one static colour table for all steps: object ids keep their colours
    assert rec.steps("/world", "AnnotationContext:context") == [None]


def _rgb(color) -> int:
    r, g, b = color
    return (r << 24) | (g << 16) | (b << 8) | 255


def test_3d_views_open_framed_on_the_workspace_without_labels_or_depth_clouds(synthetic):
    rec = synthetic["rec"]
    eyes = rec.blueprint_rows["EyeControls3D:position"]
    assert len(eyes) == 2  # both 3D views: ground truth, predictions vs ground truth
    for eye, target in zip(eyes, rec.blueprint_rows["EyeControls3D:look_target"]):
        np.testing.assert_allclose(eye[0], EYE_POSITION, atol=1e-6)
        np.testing.assert_allclose(target[0], EYE_TARGET, atol=1e-6)
    # the eye sits within a metre of the workspace and above the table: the 0.512 m grid fills the view
    assert 0.3 < float(np.linalg.norm(np.subtract(EYE_POSITION, EYE_TARGET))) < 1.0 and EYE_POSITION[2] > 0.2
    queries = [q for rows in rec.blueprint_rows["ViewContents:query"] for q in rows]
    # camera images stay in their 2D views (a depth image drawn in 3D is a cloud coloured by depth)
    assert "- /world/cameras/front/image/depth" in queries and "- /world/cameras/front/image/color" in queries
    assert "- $origin/depth" in queries and "$origin/depth" in queries  # the camera's colour, its depth apart
    for entity in ("/world/gt/mask", "/world/objects/1/label", "/world/push", "/world/pred/mask"):
        shown = [c for (e, c) in rec.rows if e == entity and c.endswith(":show_labels")]
        assert shown, entity
        assert not any(v for c in shown for v in np.concatenate(rec.values(entity, c))), entity


def test_plan_view_opens_framed_on_the_workspace(tmp_path):
    import rerun as rr

    from dsr_bench.viewer.plan import plan_blueprint

    rec = rr.RecordingStream("dsr-bench", recording_id="plan-test")
    rec.save(tmp_path / "plan.rrd", default_blueprint=plan_blueprint())
    rec.disconnect()
    (eye,) = Recording(tmp_path / "plan.rrd").blueprint_rows["EyeControls3D:position"]
    np.testing.assert_allclose(eye[0], EYE_POSITION, atol=1e-6)


def test_ground_truth_cloud_is_coloured_by_the_camera_image(synthetic):
    rec = synthetic["rec"]
    assert rec.steps("/world/gt/cloud", "Points3D:positions") == [0, 2, 4, 6]
    positions = rec.values("/world/gt/cloud", "Points3D:positions", 3)
    colors = rec.values("/world/gt/cloud", "Points3D:colors")
    with SequenceReader(synthetic["seq"]) as seq:
        for t in (0, STEPS):
            expected, rgb = colored_cloud(seq.read("cameras/front/points", t), seq.read("cameras/front/color", t),
                                          margin=0.01)
            assert len(expected) > 1000
            np.testing.assert_allclose(positions[t], expected, atol=1e-6)
            packed = (rgb[:, 0].astype(np.uint32) << 24) | (rgb[:, 1].astype(np.uint32) << 16) \
                | (rgb[:, 2].astype(np.uint32) << 8) | 255
            np.testing.assert_array_equal(colors[t].astype(np.uint32), packed)
    assert len({int(c) for c in colors[0]}) > 1  # the image's colours, not one flat colour


def test_colored_cloud_keeps_the_workspace_and_drops_missing_returns():
    points = np.array([[[0.5, 0.0, 0.05], [np.nan, np.nan, np.nan]], [[0.5, 0.0, -0.005], [2.0, 0.0, 0.0]]])
    color = np.arange(12, dtype=np.uint8).reshape(2, 2, 3)
    pos, rgb = colored_cloud(points, color, margin=0.01)
    np.testing.assert_allclose(pos, [[0.5, 0.0, 0.05], [0.5, 0.0, -0.005]], atol=1e-7)
    assert rgb.tolist() == [[0, 1, 2], [6, 7, 8]]
    assert len(colored_cloud(points, color)[0]) == 1  # without the margin the point under the table goes


def test_sequence_without_policy_data(synthetic, tmp_path):
    path = shutil.copy(synthetic["seq"], tmp_path / "seq_0003.h5")
    with h5py.File(path, "a") as f:  # like an official import: no policy group
        del f["policy"]
    rrd = tmp_path / "out.rrd"
    assert main(["view", str(path), "--save", str(rrd)]) == 0
    rec = Recording(rrd)
    assert not any(entity.startswith("/policy/") and "probs" in entity for entity, _ in rec.rows)
    assert ("/world/push/chosen", "Boxes3D:centers") not in rec.rows
    assert rec.steps("/world/push", "Arrows3D:vectors") == [1, 3, 5]


def test_amodal_voxels_per_observation(synthetic):
    rec = synthetic["rec"]
    assert rec.steps("/world/gt/mask", "Points3D:positions") == [0, 2, 4, 6]
    positions = rec.values("/world/gt/mask", "Points3D:positions", 3)
    class_ids = rec.values("/world/gt/mask", "Points3D:class_ids")
    with SequenceReader(synthetic["seq"]) as seq:
        for t in range(STEPS + 1):
            mask = seq.read("mask_3d", t)
            idx = np.argwhere(mask > 0)
            np.testing.assert_allclose(positions[t], voxel_to_world(idx), atol=1e-6)
            np.testing.assert_array_equal(class_ids[t], mask[tuple(idx.T)])
            tsdf = seq.read("tsdf", t)
            assert len(rec.values("/world/tsdf", "Points3D:positions", 3)[t]) == int(((tsdf < 0) & (tsdf > -1)).sum())


def test_push_poses_and_cameras(synthetic):
    rec = synthetic["rec"]
    with SequenceReader(synthetic["seq"]) as seq:
        start, end, poses = seq.read("push_start"), seq.read("push_end"), seq.read("object_poses")
        cam = seq.camera("front")
        chosen = seq.read("policy/chosen_object")
        probs = seq.read("policy/direction_probs")
    assert rec.steps("/world/push", "Arrows3D:origins") == [1, 3, 5]
    np.testing.assert_allclose(np.concatenate(rec.values("/world/push", "Arrows3D:origins", 3)), start, atol=1e-6)
    np.testing.assert_allclose(np.concatenate(rec.values("/world/push", "Arrows3D:vectors", 3)), end - start, atol=1e-6)
    assert rec.steps("/world/push", "Clear:is_recursive") == [2, 4, 6]  # a push shows on its own tick only
    labels = [str(v[0]) for _, v in rec.rows["/world/push/chosen", "Boxes3D:labels"]]
    assert labels == [f"chosen: {k + 1}" for k in chosen]
    np.testing.assert_allclose(np.stack(rec.values("/policy/direction_probs", "BarChart:values")), probs, atol=1e-6)
    for i in range(OBJECTS):
        entity = f"/world/objects/{i + 1}"
        assert rec.steps(entity, "Transform3D:translation") == [0, 2, 4, 6]
        translations = np.concatenate(rec.values(entity, "Transform3D:translation", 3))
        np.testing.assert_allclose(translations, poses[:, i, :3], atol=1e-6)
        quaternions = np.concatenate(rec.values(entity, "Transform3D:quaternion", 4))
        np.testing.assert_allclose(quaternions, poses[:, i, 3:], atol=1e-6)  # (qx, qy, qz, qw) as stored
        assert rec.steps(entity, "Mesh3D:vertex_positions") == [None]  # the mesh is static, posed per step
    (translation,) = rec.values("/world/cameras/front", "Transform3D:translation", 3)
    np.testing.assert_allclose(translation[0], cam.extrinsics[:3, 3], atol=1e-6)
    (pinhole,) = rec.values("/world/cameras/front/image", "Pinhole:image_from_camera")
    np.testing.assert_allclose(pinhole.reshape(3, 3).T, cam.intrinsics, rtol=1e-6)  # stored column-major
    assert rec.steps("/world/cameras/front/image/color", "Image:buffer") == [0, 2, 4, 6]
    assert rec.steps("/world/cameras/front/image/mask", "SegmentationImage:buffer") == [0, 2, 4, 6]


def test_flow_arrows_are_the_ground_truth_flow(synthetic):
    rec = synthetic["rec"]
    assert rec.steps("/world/gt/flow", "Arrows3D:origins") == [1, 3, 5]
    origins = rec.values("/world/gt/flow", "Arrows3D:origins", 3)
    vectors = rec.values("/world/gt/flow", "Arrows3D:vectors", 3)
    with SequenceReader(synthetic["seq"]) as seq:
        for t in range(STEPS):
            mask, flow = seq.read("mask_3d", t), seq.read("scene_flow_3d", t)
            assert 0 < len(origins[t]) == min(MAX_ARROWS, int((mask > 0).sum()))
            idx = np.rint(world_to_voxel(origins[t].astype(np.float64))).astype(int)
            assert np.all(mask[tuple(idx.T)] > 0)
            expected = flow[:, idx[:, 0], idx[:, 1], idx[:, 2]].T[:, [1, 0, 2]] * VOXEL_SIZE  # (dy,dx,dz) -> (x,y,z) m
            np.testing.assert_allclose(vectors[t], expected, atol=1e-6)


def test_predictions_matched_disagreement_and_metrics(synthetic):
    from dsr_bench.scoring.evaluate import score_sequence

    rec, gt, mask = synthetic["rec"], synthetic["pred"]["gt"], synthetic["pred"]["mask"]
    assert rec.steps("/world/pred/mask", "Points3D:class_ids") == [0, 2, 4]  # the mask of observation t: tick 2t
    for t, ids in enumerate(rec.values("/world/pred/mask", "Points3D:class_ids")):
        # slots relabelled to the objects they match: object voxels carry the GT ids, the corner is unmatched
        assert sorted(set(ids.tolist())) == sorted(set(np.unique(gt[t]).tolist()) - {0}) + [UNMATCHED]
        assert len(ids) == int((mask[t] > 0).sum())
    inverse = np.array([0, 2, UNMATCHED, 1], np.uint8)  # slot -> object of the permutation in _predictions
    counts = {"wrong_object": 5, "only_predicted": 4 * 4 * 4, "only_true": 0}  # mislabelled voxels, the corner block
    for kind, color in COMPARE_COLORS.items():
        entity = f"/world/pred/compare/{kind}"
        assert rec.steps(entity, "Points3D:positions") == [0, 2, 4]
        assert rec.steps("/world/pred", "Clear:is_recursive") == [2, 4, 6]  # gone at the last observation
        assert [int(c) for c in np.concatenate(rec.values(entity, "Points3D:colors"))] == [_rgb(color)] * STEPS
        for t, points in enumerate(rec.values(entity, "Points3D:positions", 3)):
            matched = inverse[mask[t]]
            expected = {"correct": (matched == gt[t]) & (gt[t] > 0), "wrong_object": (matched != gt[t]) & (
                matched > 0) & (gt[t] > 0), "only_predicted": (matched > 0) & (gt[t] == 0),
                "only_true": (matched == 0) & (gt[t] > 0)}[kind]
            assert len(points) == counts.get(kind, int(expected.sum()))
            np.testing.assert_allclose(points, voxel_to_world(np.argwhere(expected)), atol=1e-6)
    pred_vectors = rec.values("/world/pred/flow", "Arrows3D:vectors", 3)
    assert rec.steps("/world/pred/flow", "Arrows3D:vectors") == [1, 3, 5]
    assert np.all(pred_vectors[0][:, 1] > 0)  # +1 voxel in dy is +4 mm along world y
    # prediction and truth in two colours, whatever the magnitudes
    assert {int(c) for c in np.concatenate(rec.values("/world/pred/flow", "Arrows3D:colors"))} == {
        _rgb(PRED_FLOW_COLOR)}
    assert {int(c) for c in np.concatenate(rec.values("/world/gt/flow", "Arrows3D:colors"))} == {_rgb(GT_FLOW_COLOR)}
    pred_file = synthetic["pred_dir"] / "seq_0007.h5"
    _, problems, expected = score_sequence(("seq_0007", str(pred_file), str(synthetic["seq"])))
    assert not problems
    for key in ("iou_unordered", "iou_ordered", "motion_full", "motion_visible"):
        assert rec.steps(f"/metrics/{key}", "Scalars:scalars") == [1, 3, 5]
        logged = np.concatenate(rec.values(f"/metrics/{key}", "Scalars:scalars"))
        np.testing.assert_allclose(logged, expected[key], rtol=1e-9)
    assert all(v < 1 for v in expected["iou_unordered"])  # the corner block costs IoU


def test_compare_voxels_partitions_both_masks():
    truth = np.zeros((4, 4, 2), np.uint8)
    truth[0], truth[1] = 1, 2
    matched = truth.copy()
    matched[1, 0] = 1  # object 2 predicted as object 1: 2 voxels
    matched[0, 1] = 0  # missed: 2 voxels
    matched[3, 3] = 2  # extra: 2 voxels
    kinds = compare_voxels(matched, truth)
    assert {k: len(v) for k, v in kinds.items()} == {"correct": 12, "wrong_object": 2, "only_predicted": 2,
                                                       "only_true": 2}
    union = np.concatenate(list(kinds.values()))
    assert len({tuple(v) for v in union}) == len(union) == int(((matched > 0) | (truth > 0)).sum())


def test_match_slots_inverts_a_permutation():
    gt = np.zeros((8, 8, 4), np.uint8)
    gt[:2], gt[4:6], gt[7] = 1, 2, 3
    perm = np.array([0, 4, 2, 1, 0], np.uint8)  # objects 1, 2, 3 -> slots 4, 2, 1; slot 3 empty
    pred = perm[gt]
    pred[2, 0, 0] = 3  # a stray slot: no object left to match it
    lut = match_slots(pred, gt, num_slots=4, num_objects=3)
    assert lut.tolist() == [0, 3, 2, UNMATCHED, 1]
    assert np.array_equal(lut[perm[gt]], gt)


def test_real_generated_sequence_end_to_end(generated_dataset, tmp_path):
    pred = tmp_path / "pred"
    assert main(["predict", "--model", "static", "--data", str(generated_dataset), "--out", str(pred)]) == 0
    rrd = tmp_path / "seq_0001.rrd"
    assert main(["view", "seq_0001", "--data", str(generated_dataset), "--predictions", str(pred),
                 "--save", str(rrd)]) == 0
    assert subprocess.run([_rerun(), "rrd", "verify", str(rrd)], capture_output=True).returncode == 0
    rec = Recording(rrd)
    with SequenceReader(generated_dataset / "seq_0001.h5") as seq:
        steps, objects = seq.num_steps, seq.num_objects
    assert rec.steps("/world/gt/mask", "Points3D:positions") == list(range(0, 2 * steps + 1, 2))
    assert rec.steps("/metrics/motion_full", "Scalars:scalars") == list(range(1, 2 * steps, 2))
    assert all(rec.steps(f"/world/objects/{i + 1}", "Mesh3D:vertex_positions") == [None] for i in range(objects))


def _fails(capsys, argv: list[str], message: str) -> None:
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and message in err, err


def test_errors(synthetic, tmp_path, capsys):
    data = synthetic["seq"].parent
    out = tmp_path / "out"
    _fails(capsys, ["view", "seq_0099", "--data", str(data), "--save", str(out / "a.rrd")],
           f"no sequence 'seq_0099' in {data}: it holds seq_0007 (1 sequence)")  # no manifest: no `info` to point at
    _fails(capsys, ["view", "seq_0099", "--data", str(tmp_path), "--save", str(out / "a.rrd")],
           "it holds no seq_*.h5 files; give --data a dataset directory")
    _fails(capsys, ["view", "seq_0007", "--save", str(out / "a.rrd"), "--grpc-port", "9876"], "add --web")
    broken = tmp_path / "broken.h5"
    broken.write_bytes(b"\x89HDF\r\n garbage")
    _fails(capsys, ["view", str(broken), "--save", str(out / "b.rrd")], "not a readable HDF5 file")
    partial = shutil.copy(synthetic["seq"], tmp_path / "partial.h5")
    with h5py.File(partial, "a") as f:
        del f["scene_flow_3d"]
    _fails(capsys, ["view", str(partial), "--save", str(out / "c.rrd")], "missing dataset 'scene_flow_3d'")
    _fails(capsys, ["view", "seq_0007", "--data", str(data), "--predictions", str(tmp_path / "none"),
                    "--save", str(out / "d.rrd")], "predictions directory not found")
    (tmp_path / "empty").mkdir()
    _fails(capsys, ["view", "seq_0007", "--data", str(data), "--predictions", str(tmp_path / "empty"),
                    "--save", str(out / "e.rrd")], "no prediction file for seq_0007")
    bad = tmp_path / "bad"
    bad.mkdir()
    with h5py.File(bad / "seq_0007.h5", "w") as f:
        f.attrs["num_slots"] = 3
        f["mask"] = np.zeros((STEPS, 4, 4, 4), np.uint8)
    _fails(capsys, ["view", "seq_0007", "--data", str(data), "--predictions", str(bad), "--save", str(out / "f.rrd")],
           "invalid predictions")
    _fails(capsys, ["view", "seq_0007", "--data", str(data), "--save", str(out / "g.rrd"), "--web"], "--save and --web")
    _fails(capsys, ["view", "seq_0007", "--data", str(data), "--save", str(out / "g.txt")], "must end in .rrd")
    assert not out.exists() or not any(out.iterdir())  # nothing half-written


def test_native_viewer_needs_a_display(synthetic, monkeypatch, capsys):
    monkeypatch.setattr(sys, "platform", "linux")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    _fails(capsys, ["view", str(synthetic["seq"])], "--save out.rrd, or serve it with --web")


def test_predictions_name_the_dataset(synthetic, tmp_path, capsys):
    """--predictions without --data: the dataset is the one the predictions' meta.json names, said on one line."""
    from dsr_bench.scoring.predictions import record_source

    data, pred = synthetic["seq"].parent, tmp_path / "pred"
    shutil.copytree(synthetic["pred_dir"], pred)
    _fails(capsys, ["view", "seq_0007", "--predictions", str(pred), "--save", str(tmp_path / "a.rrd")],
           f"{pred / 'meta.json'} not found, so the dataset of these predictions is unknown; give it with --data DIR")
    record_source(pred, data, "test")
    assert main(["view", "seq_0007", "--predictions", str(pred), "--save", str(tmp_path / "b.rrd")]) == 0
    assert f"data: {data.resolve()} (from {pred / 'meta.json'})" in capsys.readouterr().err.splitlines()
    assert Recording(tmp_path / "b.rrd").steps("/world/pred/mask", "Points3D:positions")


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _listening(port: int) -> bool:
    import socket

    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) == 0


def test_web_viewer_serves_page_and_data_and_says_both_ports(synthetic, monkeypatch, capsys):
    """`view --web` prints one line with the URL and both ports the browser needs, and keeps serving both (the
    data's gRPC server stops if its recording stream is dropped) until Ctrl-C."""
    import gc
    import time

    page, data = _free_port(), _free_port()
    sleep = time.sleep

    def interrupt(seconds: float) -> None:  # the command's wait for Ctrl-C: check the servers, then press it
        if seconds < 3600:
            return sleep(seconds)
        gc.collect()
        assert _listening(page) and _listening(data), (page, data)
        raise KeyboardInterrupt

    monkeypatch.setattr(time, "sleep", interrupt)
    assert main(["view", str(synthetic["seq"]), "--web", "--web-port", str(page), "--grpc-port", str(data)]) == 130
    out = capsys.readouterr().out
    assert out.count("\n") == 1 and out.startswith(f"serving the web viewer at http://localhost:{page}/?url=")
    assert f"port {page}" in out and f"port {data} (rerun's gRPC server)" in out
    assert f"ssh -L {page}:localhost:{page} -L {data}:localhost:{data} HOST" in out


def test_2d_only_predictions_show_the_2d_flow_and_its_metric(synthetic, tmp_path):
    """A 2D-only prediction (motion_2d alone): no 3D prediction entities, its flow as arrows from the front
    camera's points (components (dy, dx, dz) -> world (x, y, z)), its per-step 2D metric as evaluate computes it."""
    from dsr_bench.scoring.evaluate import score_sequence

    with SequenceReader(synthetic["seq"]) as seq:
        flow = seq.read("cameras/front/scene_flow_2d").astype(np.float32)
        points = seq.read("cameras/front/points", slice(0, STEPS))
    flow[..., 0] += 0.01  # +1 cm in dy everywhere: every pixel with a point gets an arrow
    pred = tmp_path / "pred"
    write_predictions(pred / "seq_0007.h5", motion_2d=flow)
    rrd = tmp_path / "two_d.rrd"
    assert main(["view", "seq_0007", "--data", str(synthetic["seq"].parent), "--predictions", str(pred),
                 "--save", str(rrd)]) == 0
    rec = Recording(rrd)
    assert not rec.steps("/world/pred/mask", "Points3D:positions") and not rec.steps("/world/pred/flow",
                                                                                        "Arrows3D:vectors")
    assert rec.steps("/world/pred/flow_2d", "Arrows3D:vectors") == [1, 3, 5]
    origins = rec.values("/world/pred/flow_2d", "Arrows3D:origins", 3)
    vectors = rec.values("/world/pred/flow_2d", "Arrows3D:vectors", 3)
    for t in range(STEPS):
        finite = np.all(np.isfinite(points[t]), -1)
        assert len(origins[t]) == min(MAX_ARROWS, int(finite.sum()))
        # each arrow starts at a pixel's world point and carries that pixel's flow, reordered to (x, y, z)
        keys = {tuple(np.round(p, 5)): f for p, f in zip(points[t][finite], flow[t][finite])}
        for o, v in zip(origins[t][:50], vectors[t][:50]):
            np.testing.assert_allclose(v, keys[tuple(np.round(o, 5))][[1, 0, 2]], atol=1e-6)
    _, problems, expected = score_sequence(("seq_0007", str(pred / "seq_0007.h5"), str(synthetic["seq"])))
    assert not problems and expected["has_3d"] is False
    logged = np.concatenate(rec.values("/metrics/motion_2d", "Scalars:scalars"))
    np.testing.assert_allclose(logged, expected["motion_2d"], rtol=1e-9)
    np.testing.assert_allclose(logged, 1.0, rtol=1e-4)  # 1 cm off on every object pixel: 1 cm²
    assert not rec.steps("/metrics/iou_ordered", "Scalars:scalars")

"""The rerun viewer of sequences and predictions (`dsr-bench view`).

Everything is read through `SequenceReader`; rerun is imported lazily (`import_rerun`: without it, a one-line
UserError naming the viewer extra). Timelines: `step`, where
tick 2t is observation t and tick 2t + 1 is push t (its arrow, the flow t -> t+1 and the
predictions made at t), and `observation` (t on both). World frame: metres, z up. Entity tree:

  description                    markdown summary of the sequence
  world/cameras/<cam>            camera pose (Transform3D, camera-to-world); image: Pinhole (OpenCV
                                 axes) with image/{color,depth,mask}
  world/gt/cloud                 the front camera's points in the workspace, coloured by its RGB image
  world/tsdf                     TSDF surface band (-1 < tsdf < 0) as points
  world/gt/mask                  amodal voxels, class id = object id (AnnotationContext: stable colours)
  world/gt/flow                  scene-flow arrows t -> t+1 (subsampled), coloured by magnitude
  world/objects/<id>             object mesh (when embedded) posed by Transform3D; <id>/label its name
  world/push                     the push: start point, direction and length; world/push/chosen box
  world/pred/mask                predicted voxels, slots relabelled to their matched object's id
  world/pred/flow                predicted flow arrows
  world/pred/compare/<kind>      the matched prediction against the ground truth voxel by voxel: correct,
                                 wrong_object, only_predicted, only_true (one colour each, COMPARE_COLORS)
  world/pred/flow_2d             predicted front-camera flow (motion_2d) as arrows from the pixels' world
                                 points (subsampled); a 2D-only prediction shows this alone
  policy/{object,direction}_probs  the policy's distributions (bar charts); policy/heightmap its input
  metrics/<name>                 per-step metrics of the predictions, as `dsr-bench evaluate` computes them
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dsr_bench.atomic import atomic_path
from dsr_bench.constants import GRID_BOUNDS, VOXEL_SIZE, WORKSPACE_CENTER
from dsr_bench.errors import UserError
from dsr_bench.geometry import voxel_to_world
from dsr_bench.dataset.sequence import SequenceReader

APP_ID = "dsr-bench"
MAX_ARROWS = 1500
UNMATCHED = 255  # class id of predicted voxels whose slot matches no object
PALETTE = np.array([[230, 25, 75], [60, 180, 75], [0, 130, 200], [245, 130, 48], [145, 30, 180],
                    [70, 240, 240], [240, 50, 230], [210, 245, 60], [250, 190, 212], [0, 128, 128]], np.uint8)
PUSH_COLOR = (255, 215, 0)
GT_FLOW_COLOR = (40, 220, 40)  # ground-truth flow arrows: green
PRED_FLOW_COLOR = (255, 40, 255)  # predicted flow arrows: magenta
#: Colours of the voxel-by-voxel comparison of a matched prediction with the ground-truth amodal mask.
COMPARE_COLORS = {"correct": (170, 170, 170),  # the same object on both sides: grey
                  "wrong_object": (255, 150, 0),  # occupied on both sides, by different objects: orange
                  "only_predicted": (255, 30, 30),  # predicted where the truth is empty: red
                  "only_true": (30, 120, 255)}  # the truth where nothing is predicted (missed): blue
#: Where the 3D views open: an eye above and in front of the workspace (world x, y, z in metres, z up), looking
#: at its centre on the table, so the 0.512 m grid fills the view instead of lying edge-on far away.
EYE_POSITION = (WORKSPACE_CENTER[0], WORKSPACE_CENTER[1] - 0.42, 0.42)
EYE_TARGET = (WORKSPACE_CENTER[0], WORKSPACE_CENTER[1], 0.03)
CLOUD_CAMERA = "front"
METRIC_NAMES = ("iou_unordered", "iou_ordered", "motion_visible", "motion_full", "motion_moved", "motion_static",
                "motion_2d")
_READ_ERRORS = (OSError, KeyError, ValueError, IndexError)
#: Recordings serving the web viewer's data: a RecordingStream's gRPC server stops when the stream is dropped.
_SERVING: list = []
#: how to install what the viewer needs (pyproject.toml's viewer extra: rerun-sdk)
INSTALL = "pip install 'dsr-bench[viewer]'"


def import_rerun():
    """The rerun module; a one-line UserError naming the viewer extra where it is not installed."""
    try:
        import rerun
    except ImportError as exc:
        if (exc.name or "").split(".")[0] != "rerun":
            raise
        raise UserError(f"the viewer needs rerun (the rerun-sdk package), which is not installed: {INSTALL}") from None
    return rerun


def object_color(object_id: int) -> tuple[int, int, int]:
    """RGB colour of object id 1..N (stable across steps, views and runs)."""
    r, g, b = (int(c) for c in PALETTE[(object_id - 1) % len(PALETTE)])
    return r, g, b


def obs_tick(t: int) -> int:
    """Tick of observation t on the `step` timeline."""
    return 2 * t


def push_tick(t: int) -> int:
    """Tick of push t (and the flow and predictions t -> t+1) on the `step` timeline."""
    return 2 * t + 1


def magnitude_colors(values: np.ndarray) -> np.ndarray:
    """(N, 3) uint8 colours from blue (0) to red (the largest value) for non-negative magnitudes (N,)."""
    scale = values / max(float(values.max(initial=0.0)), 1e-9)
    return np.stack([255 * scale, 60 * np.ones_like(scale), 255 * (1 - scale)], 1).astype(np.uint8)


def flow_arrows(flow: np.ndarray, mask: np.ndarray, rng: np.random.Generator,
                max_arrows: int = MAX_ARROWS) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Arrows (origins, vectors in metres, world (x, y, z); colours) at up to `max_arrows` random
    voxels where `mask` (Y, X, Z) > 0, from a flow volume (3, Y, X, Z) in voxels, (dy, dx, dz)."""
    idx = np.argwhere(mask > 0)
    if len(idx) > max_arrows:
        idx = idx[np.sort(rng.choice(len(idx), max_arrows, replace=False))]
    vec_yxz = np.asarray(flow[:, idx[:, 0], idx[:, 1], idx[:, 2]], dtype=np.float64).T
    vectors = vec_yxz[:, [1, 0, 2]] * VOXEL_SIZE
    return voxel_to_world(idx), vectors, magnitude_colors(np.linalg.norm(vectors, axis=1))


def match_slots(pred_mask: np.ndarray, gt_mask: np.ndarray, num_slots: int, num_objects: int) -> np.ndarray:
    """Lookup table (num_slots + 1,) uint8 from predicted slot to the GT object id it matches under the
    benchmark's per-step (unordered) Hungarian matching; 0 -> 0, unmatched slots -> UNMATCHED."""
    from dsr_bench.matching import assignment, overlap

    ov = overlap(pred_mask, gt_mask, num_slots, num_objects)
    rows, cols = assignment(ov.iou)
    lut = np.full(num_slots + 1, UNMATCHED, np.uint8)
    lut[0] = 0
    keep = ov.inter[rows, cols] > 0
    lut[rows[keep] + 1] = cols[keep] + 1
    return lut


def flow_2d_arrows(flow_2d: np.ndarray, points: np.ndarray, rng: np.random.Generator,
                   max_arrows: int = MAX_ARROWS) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Arrows (origins world (x, y, z) m, vectors world (x, y, z) m; colours) at up to `max_arrows` random pixels
    with a finite world point and a non-zero flow, from a front-camera flow (H, W, 3) in metres, (dy, dx, dz),
    and the camera's world points (H, W, 3) in (x, y, z) metres (NaN: no return)."""
    flow = np.asarray(flow_2d, dtype=np.float64)
    idx = np.argwhere(np.all(np.isfinite(points), -1) & np.any(flow != 0, -1))
    if len(idx) > max_arrows:
        idx = idx[np.sort(rng.choice(len(idx), max_arrows, replace=False))]
    vectors = flow[idx[:, 0], idx[:, 1]][:, [1, 0, 2]]
    origins = np.asarray(points[idx[:, 0], idx[:, 1]], dtype=np.float64)
    return origins, vectors, magnitude_colors(np.linalg.norm(vectors, axis=1))


def compare_voxels(matched: np.ndarray, truth: np.ndarray) -> dict[str, np.ndarray]:
    """Voxel indices (N, 3), (y, x, z), of each kind in COMPARE_COLORS, from a prediction relabelled to object ids
    (`match_slots`) and the ground-truth amodal mask, both (Y, X, Z): correct (same object), wrong_object (both
    occupied, by different objects), only_predicted (truth empty), only_true (prediction empty)."""
    pred, true = matched > 0, truth > 0
    return {"correct": np.argwhere(pred & true & (matched == truth)),
            "wrong_object": np.argwhere(pred & true & (matched != truth)),
            "only_predicted": np.argwhere(pred & ~true),
            "only_true": np.argwhere(~pred & true)}


def colored_cloud(points: np.ndarray, color: np.ndarray, margin: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """(positions (N, 3) world (x, y, z) m, colours (N, 3) uint8) of a camera's world points (H, W, 3) (NaN: no
    return) and its colour image (H, W, 3), kept inside the voxel grid's bounds (GRID_BOUNDS) grown by `margin` m."""
    lo, hi = GRID_BOUNDS[:, 0] - margin, GRID_BOUNDS[:, 1] + margin
    with np.errstate(invalid="ignore"):
        keep = np.all((points >= lo) & (points <= hi), -1)  # NaN compares False: dropped
    return np.asarray(points[keep], dtype=np.float32), np.asarray(color[keep], dtype=np.uint8)


def check_sequence(seq: SequenceReader) -> None:
    """Raise UserError naming every structural problem (missing datasets, shapes, dtypes) of a sequence."""
    from dsr_bench.dataset.validate import schema_problems

    problems, _ = schema_problems(seq)
    if problems:
        raise UserError(f"{seq.path}: not a valid sequence ({'; '.join(problems)}); run `dsr-bench validate` on it")


def load_predictions(pred_dir: Path, seq: SequenceReader) -> dict:
    """The predictions for `seq` in `pred_dir`, checked against the contract, and their per-step
    metrics exactly as `dsr-bench evaluate` computes them: {mask, motion, num_slots, [motion_2d,] metrics};
    a 2D-only prediction: {motion_2d, metrics}."""
    import h5py

    from dsr_bench.scoring.evaluate import require_predictions_dir, score_sequence
    from dsr_bench.scoring.predictions import check_prediction_header

    pred_dir = require_predictions_dir(pred_dir)
    path = pred_dir / f"{seq.path.stem}.h5"
    if not path.is_file():
        raise UserError(f"no prediction file for {seq.path.stem} in {pred_dir} (expected {path.name})")
    try:
        with h5py.File(path, "r") as f:
            problems = check_prediction_header(f, seq.num_steps)
            if not problems:
                pred = {"motion_2d": f["motion_2d"][()]} if "motion_2d" in f else {}
                if "mask" in f:  # else a 2D-only prediction
                    pred.update(mask=f["mask"][()], motion=f["motion"][()], num_slots=int(f.attrs["num_slots"]))
    except _READ_ERRORS as exc:
        problems = [f"unreadable ({type(exc).__name__}: {exc})"]
    if not problems:
        _, problems, values = score_sequence((seq.path.stem, str(path), str(seq.path)))
    if problems or values is None:  # values: None only with problems
        raise UserError(f"{path}: invalid predictions ({'; '.join(problems)}); see `dsr-bench evaluate`")
    pred["metrics"] = {k: np.asarray(values[k], dtype=np.float64) for k in METRIC_NAMES
                       if k in values and (k != "motion_2d" or values.get("has_2d"))}
    return pred


def workspace_eye():
    """The 3D views' eye: EYE_POSITION looking at EYE_TARGET, z up (a rerun `EyeControls3D`)."""
    import rerun.blueprint as rrb

    return rrb.EyeControls3D(position=EYE_POSITION, look_target=EYE_TARGET, eye_up=(0.0, 0.0, 1.0))


def blueprint(cameras: list[str], has_predictions: bool, has_policy: bool = True):
    """A layout that opens ready to read: the 3D views framed on the workspace (EYE_POSITION looking at
    EYE_TARGET), the ground truth on top and the prediction against it below, beside the camera views and charts."""
    import rerun.blueprint as rrb

    # camera images stay in their 2D views: drawn in 3D, a depth image is a cloud coloured by depth
    hide_images = [f"- /world/cameras/{c}/image/{kind}" for c in cameras for kind in ("color", "depth", "mask")]
    scene = [rrb.Spatial3DView(origin="world", name="scene (ground truth)", eye_controls=workspace_eye(),
                               contents=["+ /world/**", "- /world/pred/**", "- /world/tsdf", *hide_images])]
    if has_predictions:
        scene.append(rrb.Spatial3DView(
            origin="world", name="predictions vs ground truth: grey correct, orange wrong object, red only "
            "predicted, blue missed; flow green true, magenta predicted", eye_controls=workspace_eye(),
            contents=["+ /world/pred/compare/**", "+ /world/pred/flow", "+ /world/pred/flow_2d", "+ /world/gt/flow",
                      "+ /world/push/**"]))
    # colour with the visible mask over it; the depth in a view of its own (over the colour it hid it in a rainbow)
    cams = [rrb.Spatial2DView(origin=f"world/cameras/{c}/image", name=f"{c} camera",
                              contents=["$origin/**", "- $origin/depth"]) for c in cameras]
    charts: list = [rrb.Spatial2DView(origin=f"world/cameras/{c}/image", name=f"{c} depth (m)",
                                      contents=["$origin/depth"]) for c in cameras[:1]]  # rerun views of several kinds
    if has_predictions:
        charts.append(rrb.TimeSeriesView(origin="metrics", name="per-step metrics"))
    if has_policy:
        charts += [rrb.BarChartView(origin="policy/direction_probs", name="direction probabilities (0..7)"),
                   rrb.BarChartView(origin="policy/object_probs", name="object probabilities")]
    charts += [rrb.Spatial2DView(origin="policy/heightmap", name="heightmap"),
               rrb.TextDocumentView(origin="description", name="sequence")]
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(*scene) if len(scene) > 1 else scene[0],
            rrb.Vertical(rrb.Horizontal(*cams) if cams else rrb.TextDocumentView(origin="description"),
                         rrb.Grid(*charts), row_shares=[1, 1]),
            column_shares=[3, 2],
        ),
        rrb.TimePanel(state="collapsed", play_state="paused"),
        collapse_panels=True,
    )


def _description(seq: SequenceReader) -> str:
    lines = [f"# {seq.name}", "",
             f"object set: {seq.attrs.get('object_set', '?')}, policy: {seq.attrs.get('policy', '?')}, "
             f"{seq.num_steps} pushes, {seq.num_objects} objects, cameras: {', '.join(seq.cameras)}", ""]
    lines += [f"- {i + 1}: {o.get('category', '?')} ({o.get('model_id', '?')})" for i, o in enumerate(seq.objects)]
    lines += ["", "Timeline `step`: even ticks are observations, odd ticks pushes (flow and predictions t -> t+1)."]
    return "\n".join(lines)


def _log_static(rec, rr, seq: SequenceReader) -> None:
    rec.log("description", rr.TextDocument(_description(seq), media_type=rr.MediaType.MARKDOWN), static=True)
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    infos = [rr.AnnotationInfo(id=0, label="background", color=(0, 0, 0)),
             rr.AnnotationInfo(id=UNMATCHED, label="unmatched slot", color=(128, 128, 128))]
    for i, obj in enumerate(seq.objects):
        infos.append(rr.AnnotationInfo(id=i + 1, label=f"{i + 1}: {obj.get('category', '?')}",
                                       color=object_color(i + 1)))
    context = rr.AnnotationContext(infos)
    rec.log("world", context, static=True)
    for name in seq.cameras:
        cam = seq.camera(name)
        rec.log(f"world/cameras/{name}", rr.Transform3D(translation=cam.extrinsics[:3, 3],
                                                        mat3x3=cam.extrinsics[:3, :3]), static=True)
        rec.log(f"world/cameras/{name}/image",
                rr.Pinhole(image_from_camera=cam.intrinsics, resolution=[cam.width, cam.height],
                           camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=0.1), static=True)
        rec.log(f"world/cameras/{name}/image", context, static=True)  # 2D views sit outside world's subtree
    for i, obj in enumerate(seq.objects):
        mesh = seq.mesh(i)
        if mesh is not None:
            rec.log(f"world/objects/{i + 1}",
                    rr.Mesh3D(vertex_positions=mesh[0], triangle_indices=mesh[1],
                              albedo_factor=[*(np.array(object_color(i + 1)) / 255.0), 0.5]), static=True)
        rec.log(f"world/objects/{i + 1}/label",
                rr.Points3D([[0, 0, 0]], labels=[f"{i + 1}: {obj.get('category', '?')}"], radii=0.002,
                            colors=[object_color(i + 1)], show_labels=False), static=True)  # on hover


def log_voxels(rec, rr, entity: str, labels: np.ndarray) -> None:
    """Log the labelled voxels of `labels` (Y, X, Z) as world points, class id = label, at `entity`."""
    occupied = np.argwhere(labels > 0)
    rec.log(entity, rr.Points3D(voxel_to_world(occupied), class_ids=labels[tuple(occupied.T)], radii=VOXEL_SIZE / 2,
                                show_labels=False))


def log_sequence(rec, seq: SequenceReader, predictions: dict | None = None, seed: int = 0) -> None:
    """Log one sequence (and optionally predictions from `load_predictions`) to a rerun RecordingStream."""
    import rerun as rr

    rng = np.random.default_rng(seed)
    _log_static(rec, rr, seq)
    poses = seq.read("object_poses")
    action, start, end = seq.read("action"), seq.read("push_start"), seq.read("push_end")
    has_policy = "policy/chosen_object" in seq
    for t in range(seq.num_steps + 1):
        rec.set_time("step", sequence=obs_tick(t))
        rec.set_time("observation", sequence=t)
        if t > 0:  # push t-1, its flow and the predictions made at t-1 belong to the previous ticks only
            for entity in ("world/push", "world/gt/flow", "world/pred"):
                rec.log(entity, rr.Clear(recursive=True))
        for name in seq.cameras:
            base = f"world/cameras/{name}/image"
            rec.log(f"{base}/color", rr.Image(seq.read(f"cameras/{name}/color", t)))
            rec.log(f"{base}/depth", rr.DepthImage(seq.read(f"cameras/{name}/depth", t), meter=1.0))
            rec.log(f"{base}/mask", rr.SegmentationImage(seq.read(f"cameras/{name}/mask", t)))
        rec.log("policy/heightmap", rr.DepthImage(seq.read("heightmap", t), meter=1.0,
                                                  colormap=rr.components.Colormap.Viridis))
        tsdf = seq.read("tsdf", t)
        band = np.argwhere((tsdf < 0) & (tsdf > -1))
        if CLOUD_CAMERA in seq.cameras:
            cloud, rgb = colored_cloud(seq.read(f"cameras/{CLOUD_CAMERA}/points", t),
                                       seq.read(f"cameras/{CLOUD_CAMERA}/color", t), margin=0.01)
            rec.log("world/gt/cloud", rr.Points3D(cloud, colors=rgb, radii=rr.Radius.ui_points(2.5)))  # no gaps
        rec.log("world/tsdf", rr.Points3D(voxel_to_world(band), colors=[180, 180, 180], radii=VOXEL_SIZE / 2))
        mask = seq.read("mask_3d", t)
        log_voxels(rec, rr, "world/gt/mask", mask)
        for i in range(seq.num_objects):
            rec.log(f"world/objects/{i + 1}", rr.Transform3D(translation=poses[t, i, :3],
                                                            quaternion=rr.Quaternion(xyzw=poses[t, i, 3:])))
        if t == seq.num_steps:  # the last observation has no push (nor prediction) after it
            break
        if predictions is not None and "mask" in predictions:  # the predicted mask of observation t, from tick 2t
            pm = predictions["mask"][t]
            matched = match_slots(pm, mask, predictions["num_slots"], seq.num_objects)[pm]
            log_voxels(rec, rr, "world/pred/mask", matched)
            for kind, idx in compare_voxels(matched, mask).items():
                rec.log(f"world/pred/compare/{kind}", rr.Points3D(voxel_to_world(idx), colors=[COMPARE_COLORS[kind]],
                                                                  radii=VOXEL_SIZE / 2))
        rec.set_time("step", sequence=push_tick(t))
        d, row, col = (int(v) for v in action[t])
        rec.log("world/push", rr.Arrows3D(origins=[start[t]], vectors=[end[t] - start[t]], colors=[PUSH_COLOR],
                                          radii=0.004, labels=[f"push {t}: direction {d}, cell ({row}, {col})"],
                                          show_labels=False))
        if has_policy:
            k = int(seq.read("policy/chosen_object", t))
            chosen = np.argwhere(mask == k + 1)
            if len(chosen):
                lo, hi = voxel_to_world(chosen.min(0)), voxel_to_world(chosen.max(0))
                rec.log("world/push/chosen", rr.Boxes3D(centers=[(lo + hi) / 2],
                                                        half_sizes=[np.abs(hi - lo) / 2 + VOXEL_SIZE],
                                                        colors=[PUSH_COLOR], labels=[f"chosen: {k + 1}"],
                                                        show_labels=False))
            else:
                rec.log("world/push/chosen", rr.Clear(recursive=False))
            rec.log("policy/object_probs", rr.BarChart(seq.read("policy/object_probs", t)))
            rec.log("policy/direction_probs", rr.BarChart(seq.read("policy/direction_probs", t)))
        origins, vectors, _ = flow_arrows(seq.read("scene_flow_3d", t), mask, rng)
        rec.log("world/gt/flow", rr.Arrows3D(origins=origins, vectors=vectors, colors=[GT_FLOW_COLOR]))
        if predictions is not None:
            for key, values in predictions["metrics"].items():
                if np.isfinite(values[t]):
                    rec.log(f"metrics/{key}", rr.Scalars(float(values[t])))
        if predictions is not None and "mask" in predictions:
            o, v, _ = flow_arrows(predictions["motion"][t], predictions["mask"][t], rng)
            rec.log("world/pred/flow", rr.Arrows3D(origins=o, vectors=v, colors=[PRED_FLOW_COLOR]))
        if predictions is not None and "motion_2d" in predictions and "cameras/front/points" in seq:
            o, v, _ = flow_2d_arrows(predictions["motion_2d"][t], seq.read("cameras/front/points", t), rng)
            rec.log("world/pred/flow_2d", rr.Arrows3D(origins=o, vectors=v, colors=[PRED_FLOW_COLOR]))


def _log_or_fail(rec, seq, pred, path: Path) -> None:
    """Log the sequence (and predictions) to `rec` and flush; data that cannot be read is a UserError."""
    try:
        log_sequence(rec, seq, pred)
    except _READ_ERRORS as exc:
        raise UserError(f"{path}: unreadable data ({type(exc).__name__}: {exc}); "
                        "run `dsr-bench validate` on it") from None
    rec.flush()


def web_ports(url: str) -> tuple[int | None, int | None]:
    """(web viewer port, gRPC port) of a URL that `view` returns when serving: the browser loads the page from
    the first and then streams the recording from the second, so both must be reachable."""
    from urllib.parse import parse_qs, urlsplit

    page = urlsplit(url)
    data = urlsplit(parse_qs(page.query)["url"][0].removeprefix("rerun+"))
    return page.port, data.port


def view(path: str | Path, predictions: str | Path | None = None, save: str | Path | None = None,
         web: bool = False, web_port: int | None = None, grpc_port: int | None = None) -> Path | str | None:
    """Open a sequence file in the rerun viewer, or write a recording to `save` (.rrd, atomically),
    or serve the web viewer (`web`: page on `web_port`, default 9090, data over gRPC on `grpc_port`,
    default 9876; the servers live as long as the process, which the caller keeps alive). Returns the
    written path when saving, the viewer's URL when serving (`web_ports` gives both ports)."""
    rr = import_rerun()

    path = Path(path)
    if not path.is_file():
        raise UserError(f"sequence file not found: {path}")
    with SequenceReader(path) as seq:
        check_sequence(seq)
        pred = load_predictions(Path(predictions), seq) if predictions is not None else None
        rec = rr.RecordingStream(APP_ID, recording_id=seq.name)
        bp = blueprint(list(seq.cameras), pred is not None, "policy/chosen_object" in seq)
        if save is not None:
            save = Path(save)
            save.parent.mkdir(parents=True, exist_ok=True)
            with atomic_path(save) as tmp:  # renamed to `save` once the recording is complete (dsr_bench.atomic)
                try:
                    rec.save(tmp, default_blueprint=bp)
                    _log_or_fail(rec, seq, pred, path)
                finally:
                    rec.disconnect()
            return save
        if web:
            from urllib.parse import quote

            uri = rec.serve_grpc(grpc_port=grpc_port, default_blueprint=bp)
            _SERVING.append(rec)  # dropping the stream would stop its gRPC server: the page would show no data
            rr.serve_web_viewer(web_port=web_port, open_browser=False, connect_to=uri)
            url = f"http://localhost:{web_port or 9090}/?url={quote(uri, safe='')}"
        else:
            rec.spawn(default_blueprint=bp)
        _log_or_fail(rec, seq, pred, path)
        if web:
            return url
    return None

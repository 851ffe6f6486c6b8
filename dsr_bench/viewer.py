"""The rerun viewer of sequences and predictions (`dsr-bench view`).

Everything is read through `SequenceReader`; rerun is imported lazily. Timeline `step`: tick 2t
is observation t, tick 2t + 1 is push t (its arrow, the flow t -> t+1 and the predictions made at
t). Entity tree:

  world/cameras/<cam>            camera pose (Transform3D) and Pinhole; image/{color,depth,mask}
  world/tsdf                     TSDF surface band (-1 < tsdf < 0) as points
  world/gt/mask                  amodal voxels coloured per object (AnnotationContext: stable colours)
  world/gt/flow                  scene-flow arrows (subsampled), coloured by magnitude
  world/objects/<i>              object mesh (embedded meshes) posed by Transform3D, with its name
  world/push                     the push: start, direction and length; world/push/chosen box
  world/pred/{mask,flow}         predictions; world/pred/disagree voxels where occupancy differs
  policy/{object,direction}_probs  the policy's distributions (bar charts)
  metrics/<name>                 per-step metrics of the predictions (scalars)
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dsr_bench.constants import VOXEL_SIZE
from dsr_bench.geometry import voxel_to_world
from dsr_bench.sequence import SequenceReader

APP_ID = "dsr-bench"
MAX_ARROWS = 1500
PALETTE = np.array([[230, 25, 75], [60, 180, 75], [0, 130, 200], [245, 130, 48], [145, 30, 180],
                    [70, 240, 240], [240, 50, 230], [210, 245, 60], [250, 190, 212], [0, 128, 128]], np.uint8)


def _obs_tick(t: int) -> int:
    return 2 * t


def _push_tick(t: int) -> int:
    return 2 * t + 1


def _magnitude_colors(values: np.ndarray) -> np.ndarray:
    """Blue (small) to red (large) colours for non-negative magnitudes."""
    scale = values / max(float(values.max(initial=0.0)), 1e-9)
    return np.stack([255 * scale, 60 * np.ones_like(scale), 255 * (1 - scale)], 1).astype(np.uint8)


def _flow_arrows(flow: np.ndarray, mask: np.ndarray, rng: np.random.Generator):
    """Subsampled arrows (origins, vectors, colours) in metres from a flow volume (3, Y, X, Z) in voxels."""
    idx = np.argwhere(mask > 0)
    if len(idx) > MAX_ARROWS:
        idx = idx[rng.choice(len(idx), MAX_ARROWS, replace=False)]
    vec_yxz = flow[:, idx[:, 0], idx[:, 1], idx[:, 2]].T
    vectors = vec_yxz[:, [1, 0, 2]] * VOXEL_SIZE
    return voxel_to_world(idx), vectors, _magnitude_colors(np.linalg.norm(vectors, axis=1))


def blueprint(cameras: list[str], has_predictions: bool):
    """A layout that opens ready to read: 3D scene, camera views, policy and metric charts."""
    import rerun.blueprint as rrb

    side = [rrb.Spatial2DView(origin=f"world/cameras/{c}/image", name=f"{c} camera") for c in cameras]
    charts = [rrb.BarChartView(origin="policy/direction_probs", name="direction probabilities"),
              rrb.BarChartView(origin="policy/object_probs", name="object probabilities")]
    if has_predictions:
        charts.insert(0, rrb.TimeSeriesView(origin="metrics", name="per-step metrics"))
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(origin="world", name="scene"),
            rrb.Vertical(*side, *charts),
            column_shares=[3, 2],
        ),
        rrb.TimePanel(state="expanded"),
        collapse_panels=False,
    )


def _log_static(rec, rr, seq: SequenceReader) -> None:
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    infos = [rr.AnnotationInfo(id=0, label="empty", color=(0, 0, 0))]
    for i, obj in enumerate(seq.objects):
        infos.append(rr.AnnotationInfo(id=i + 1, label=f"{i + 1}: {obj.get('category', '?')}",
                                       color=tuple(int(c) for c in PALETTE[i % len(PALETTE)])))
    rec.log("world", rr.AnnotationContext(infos), static=True)
    for name in seq.cameras:
        cam = seq.camera(name)
        rec.log(f"world/cameras/{name}", rr.Transform3D(translation=cam.extrinsics[:3, 3],
                                                        mat3x3=cam.extrinsics[:3, :3]), static=True)
        rec.log(f"world/cameras/{name}/image",
                rr.Pinhole(image_from_camera=cam.intrinsics, resolution=[cam.width, cam.height],
                           camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=0.1), static=True)
        rec.log(f"world/cameras/{name}/image", rr.AnnotationContext(infos), static=True)
    for i, obj in enumerate(seq.objects):
        mesh = seq.mesh(i)
        if mesh is not None:
            color = PALETTE[i % len(PALETTE)]
            rec.log(f"world/objects/{i + 1}", rr.Mesh3D(vertex_positions=mesh[0], triangle_indices=mesh[1],
                                                       albedo_factor=[*(color / 255.0), 0.35]), static=True)
        rec.log(f"world/objects/{i + 1}/label", rr.Points3D([[0, 0, 0]], labels=[f"{i + 1}: {obj.get('category', '?')}"],
                                                          radii=0.002), static=True)


def _step_metrics(seq: SequenceReader, pred_mask: np.ndarray, pred_motion, num_slots: int) -> dict[str, np.ndarray]:
    from dsr_bench.metrics import motion_errors, sequence_scores

    gt_mask = seq.read("mask_3d", slice(0, seq.num_steps))
    scores = sequence_scores(pred_mask, gt_mask, num_slots, seq.num_objects)
    out = {"iou_unordered": scores["iou_unordered"], "iou_ordered": scores["iou_ordered"]}
    motion = [motion_errors(pred_motion[t], seq.read("scene_flow_3d", t), seq.read("tsdf", t), gt_mask[t],
                            seq.num_objects) for t in range(seq.num_steps)]
    out["motion_visible"] = np.array([m["motion_visible"] for m in motion])
    out["motion_full"] = np.array([m["motion_full"] for m in motion])
    return out


def log_sequence(rec, seq: SequenceReader, predictions: Path | None = None) -> None:
    """Log one sequence (and optionally its predictions) to a rerun recording stream."""
    import rerun as rr

    rng = np.random.default_rng(0)
    _log_static(rec, rr, seq)
    poses = seq.read("object_poses")
    action, start, end = seq.read("action"), seq.read("push_start"), seq.read("push_end")
    has_policy = "policy/chosen_object" in seq
    pred = None
    if predictions is not None:
        import h5py

        path = Path(predictions) / f"{seq.path.stem}.h5"
        if not path.is_file():
            from dsr_bench.errors import UserError

            raise UserError(f"no prediction file for {seq.path.stem} in {predictions} (expected {path})")
        with h5py.File(path, "r") as f:
            pred = {"mask": f["mask"][()], "motion": f["motion"][()], "num_slots": int(f.attrs["num_slots"])}
        metrics = _step_metrics(seq, pred["mask"], pred["motion"], pred["num_slots"])
    for t in range(seq.num_steps + 1):
        rec.set_time("step", sequence=_obs_tick(t))
        rec.set_time("observation", sequence=t)
        for name in seq.cameras:
            base = f"world/cameras/{name}/image"
            rec.log(f"{base}/color", rr.Image(seq.read(f"cameras/{name}/color", t)))
            rec.log(f"{base}/depth", rr.DepthImage(seq.read(f"cameras/{name}/depth", t), meter=1.0))
            rec.log(f"{base}/mask", rr.SegmentationImage(seq.read(f"cameras/{name}/mask", t)))
        tsdf = seq.read("tsdf", t)
        band = np.argwhere((tsdf < 0) & (tsdf > -1))
        rec.log("world/tsdf", rr.Points3D(voxel_to_world(band), colors=[180, 180, 180], radii=VOXEL_SIZE / 2))
        mask = seq.read("mask_3d", t)
        occupied = np.argwhere(mask > 0)
        rec.log("world/gt/mask", rr.Points3D(voxel_to_world(occupied), class_ids=mask[tuple(occupied.T)],
                                             radii=VOXEL_SIZE / 2))
        for i in range(seq.num_objects):
            rec.log(f"world/objects/{i + 1}", rr.Transform3D(translation=poses[t, i, :3],
                                                            quaternion=rr.Quaternion(xyzw=poses[t, i, 3:])))
        if t == seq.num_steps:
            rec.log("world/push", rr.Clear(recursive=True))
            break
        # push t: the action, the flow t -> t+1, and the predictions made at t
        rec.set_time("step", sequence=_push_tick(t))
        d, row, col = (int(v) for v in action[t])
        rec.log("world/push", rr.Arrows3D(origins=[start[t]], vectors=[end[t] - start[t]], colors=[[255, 215, 0]],
                                          radii=0.004, labels=[f"push {t}: d={d} (row {row}, col {col})"]))
        if has_policy:
            k = int(seq.read("policy/chosen_object", t))
            chosen = np.argwhere(mask == k + 1)
            if len(chosen):
                lo, hi = voxel_to_world(chosen.min(0)), voxel_to_world(chosen.max(0))
                rec.log("world/push/chosen", rr.Boxes3D(centers=[(lo + hi) / 2], half_sizes=[(hi - lo) / 2 + VOXEL_SIZE],
                                                        colors=[[255, 215, 0]], labels=[f"chosen: {k + 1}"]))
            rec.log("policy/object_probs", rr.BarChart(seq.read("policy/object_probs", t)))
            rec.log("policy/direction_probs", rr.BarChart(seq.read("policy/direction_probs", t)))
        origins, vectors, colors = _flow_arrows(seq.read("scene_flow_3d", t), mask, rng)
        rec.log("world/gt/flow", rr.Arrows3D(origins=origins, vectors=vectors, colors=colors))
        if pred is not None:
            pm = pred["mask"][t]
            occ = np.argwhere(pm > 0)
            rec.log("world/pred/mask", rr.Points3D(voxel_to_world(occ), class_ids=pm[tuple(occ.T)],
                                                   radii=VOXEL_SIZE / 2))
            o, v, c = _flow_arrows(pred["motion"][t].astype(np.float32), pm, rng)
            rec.log("world/pred/flow", rr.Arrows3D(origins=o, vectors=v, colors=c))
            disagree = np.argwhere((pm > 0) != (mask > 0))
            rec.log("world/pred/disagree", rr.Points3D(voxel_to_world(disagree), colors=[255, 0, 0],
                                                       radii=VOXEL_SIZE / 2))
            for key, values in metrics.items():
                if np.isfinite(values[t]):
                    rec.log(f"metrics/{key}", rr.Scalars(float(values[t])))


def view(path: Path, predictions: Path | None = None, save: Path | None = None, web: bool = False) -> Path | None:
    """Open a sequence in the rerun viewer, or write a recording (`save`), or serve the web viewer."""
    import rerun as rr

    with SequenceReader(path) as seq:
        rec = rr.RecordingStream(APP_ID, recording_id=f"{seq.name}")
        bp = blueprint(list(seq.cameras), predictions is not None)
        if save is not None:
            save = Path(save)
            save.parent.mkdir(parents=True, exist_ok=True)
            tmp = save.with_name(f".{save.name}.tmp")
            rec.save(tmp, default_blueprint=bp)
        elif web:
            uri = rec.serve_grpc(default_blueprint=bp)
            rr.serve_web_viewer(connect_to=uri, open_browser=False)
        else:
            rec.spawn(default_blueprint=bp)
        rec.log("description", rr.TextDocument(
            f"# {seq.name}\n\nobject set: {seq.attrs.get('object_set')}, policy: {seq.attrs.get('policy')}, "
            f"{seq.num_steps} pushes, {seq.num_objects} objects\n\n" +
            "\n".join(f"- {i + 1}: {o.get('category')} ({o.get('model_id')})" for i, o in enumerate(seq.objects)),
            media_type=rr.MediaType.MARKDOWN), static=True)
        log_sequence(rec, seq, predictions)
        rec.flush()
        if save is not None:
            rec.disconnect()
            import os

            os.replace(tmp, save)
            return save
    return None

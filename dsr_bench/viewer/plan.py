"""The rerun viewer of a plan file (`dsr-bench view OUT/task_0000.h5`, a file of `dsr-bench plan`).

Timeline `step`: tick 2t is the state before push t (2 * 3 the final state), tick 2t + 1 push t: every candidate
as an arrow coloured by its cost (green: cheapest, red: dearest; labelled with the cost), the executed one in
yellow, and the executed candidate's predicted next masks. Entities:

  description                    markdown: task, planner, scores
  world/target/mask              the target's amodal voxels (static; class id = object id)
  world/state/mask               the true amodal voxels of the current state
  world/tsdf                     the front camera's TSDF surface band (-1 < tsdf < 0)
  world/planner/mask             the planner's masks of the current state (what it sampled around)
  world/candidates, world/push   candidate pushes (arrows) and the executed one
  world/predicted/mask           the executed candidate's predicted next masks
  camera/color                   the front camera's image
  cost/{chosen,median}           the executed candidate's cost and the candidates' median, per push
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dsr_bench.atomic import atomic_path
from dsr_bench.constants import PUSH_HEIGHT, PUSH_LENGTH, VOXEL_SIZE
from dsr_bench.errors import UserError
from dsr_bench.geometry import direction_vector, pixel_to_world, voxel_to_world


def is_plan_file(path: str | Path) -> bool:
    """Whether `path` is an HDF5 file of `dsr-bench plan` (its format attribute)."""
    import h5py

    from dsr_bench.planning.plans import PLAN_FORMAT

    try:
        with h5py.File(path, "r") as f:
            fmt = f.attrs.get("format")
    except Exception:  # noqa: BLE001 - not an HDF5 file: not a plan
        return False
    return (fmt.decode() if isinstance(fmt, bytes) else fmt) == PLAN_FORMAT


def cost_colors(costs: np.ndarray) -> np.ndarray:
    """(C, 3) uint8 from green (the lowest cost) to red (the highest); grey for NaN (not scored)."""
    c = np.asarray(costs, np.float64)
    finite = np.isfinite(c)
    out = np.full((len(c), 3), 160, np.uint8)
    if finite.any():
        lo, hi = c[finite].min(), c[finite].max()
        s = (c[finite] - lo) / max(hi - lo, 1e-9)
        out[finite] = np.stack([255 * s, 255 * (1 - s), 40 * np.ones_like(s)], 1).astype(np.uint8)
    return out


def push_arrows(actions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Origins and vectors (A, 3) world metres of pushes (A, 3) (d, row, col): from the start cell's centre at
    PUSH_HEIGHT along the direction for the commanded PUSH_LENGTH."""
    a = np.asarray(actions, np.int64).reshape(-1, 3)
    xy = pixel_to_world(a[:, 1:])
    origins = np.column_stack([xy, np.full(len(a), PUSH_HEIGHT)])
    vectors = np.column_stack([direction_vector(a[:, 0]) * PUSH_LENGTH, np.zeros(len(a))])
    return origins, vectors


def plan_blueprint():
    """The plan's layout: its 3D view framed on the workspace as `dsr-bench view`'s (`EYE_POSITION` looking at
    `EYE_TARGET`), beside the camera image, the cost plot and the description."""
    import rerun.blueprint as rrb

    from dsr_bench.viewer import workspace_eye

    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(origin="world", name="plan", eye_controls=workspace_eye(),
                              contents=["+ /world/**", "- /world/tsdf"]),
            rrb.Vertical(rrb.Spatial2DView(origin="camera", name="front camera"),
                         rrb.TimeSeriesView(origin="cost", name="cost"),
                         rrb.TextDocumentView(origin="description", name="plan")),
            column_shares=[3, 2],
        ),
        rrb.TimePanel(state="collapsed", play_state="paused"),
        collapse_panels=True,
    )


def log_plan(rec, arrays: dict, attrs: dict) -> None:
    """Log a plan (`dsr_bench.planning.plans.read_plan`) to a rerun RecordingStream."""
    import rerun as rr

    from dsr_bench.viewer import PUSH_COLOR, log_voxels, object_color

    n = arrays["target/object_poses"].shape[0]
    steps = len(arrays["actions"])
    text = [f"# {attrs.get('task', '?')}: {attrs.get('planner', '?')}", "", str(attrs.get("description", "")), "",
            (f"final IoU {attrs.get('iou', float('nan')):.3f} (start {attrs.get('start_iou', float('nan')):.3f}), "
             f"identity IoU {attrs.get('iou_identity', float('nan')):.3f}, occupancy IoU "
             f"{attrs.get('iou_occupancy', float('nan')):.3f}"), "",
            (f"{attrs.get('candidates', '?')} candidates per push, seed {attrs.get('seed', '?')}, "
             f"lambda {attrs.get('lambda', '?')}"), "",
            ("Timeline `step`: even ticks are states, odd ticks pushes (candidates coloured by cost, green "
             "cheapest; the executed one in yellow).")]
    rec.log("description", rr.TextDocument("\n".join(text), media_type=rr.MediaType.MARKDOWN), static=True)
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    infos = [rr.AnnotationInfo(id=0, label="background", color=(0, 0, 0))]
    infos += [rr.AnnotationInfo(id=i, label=str(i), color=object_color(i)) for i in range(1, max(n, 5) + 1)]
    rec.log("world", rr.AnnotationContext(infos), static=True)
    log_voxels(rec, rr, "world/target/mask", arrays["target/mask_3d"])
    for t in range(steps + 1):
        rec.set_time("step", sequence=2 * t)
        for entity in ("world/candidates", "world/push", "world/predicted"):
            rec.log(entity, rr.Clear(recursive=True))
        log_voxels(rec, rr, "world/state/mask", arrays["states/mask_3d"][t])
        tsdf = arrays["states/tsdf"][t]
        band = np.argwhere((tsdf < 0) & (tsdf > -1))
        rec.log("world/tsdf", rr.Points3D(voxel_to_world(band), colors=[180, 180, 180], radii=VOXEL_SIZE / 2))
        if "states/color" in arrays:
            rec.log("camera/color", rr.Image(arrays["states/color"][t]))
        if t == steps:
            break
        log_voxels(rec, rr, "world/planner/mask", arrays["planner_masks"][t])
        rec.set_time("step", sequence=2 * t + 1)
        costs = arrays["costs"][t]
        cands = arrays["candidates"][t]
        origins, vectors = push_arrows(cands)
        labels = [f"{c:.2f}" if np.isfinite(c) else "-" for c in costs]
        rec.log("world/candidates", rr.Arrows3D(origins=origins, vectors=vectors, colors=cost_colors(costs),
                                                radii=0.001, labels=labels, show_labels=False))
        o, v = push_arrows(arrays["actions"][t])
        chosen = int(arrays["chosen"][t])
        d, row, col = (int(x) for x in arrays["actions"][t])
        label = f"push {t}: direction {d}, cell ({row}, {col}), cost {labels[chosen]}"
        rec.log("world/push", rr.Arrows3D(origins=o, vectors=v, colors=[PUSH_COLOR], radii=0.004, labels=[label],
                                          show_labels=False))
        log_voxels(rec, rr, "world/predicted/mask", arrays["predicted"][t])
        if np.isfinite(costs[chosen]):
            rec.log("cost/chosen", rr.Scalars(float(costs[chosen])))
            rec.log("cost/median", rr.Scalars(float(np.nanmedian(costs))))


def view_plan(path: str | Path, save: str | Path | None = None, web: bool = False, web_port: int | None = None,
              grpc_port: int | None = None) -> Path | str | None:
    """Open a plan file in the rerun viewer, or write a recording to `save` (.rrd, atomically), or serve the web
    viewer; returns as `dsr_bench.viewer.view` does."""
    from dsr_bench.planning.plans import read_plan
    from dsr_bench.viewer import _SERVING, APP_ID, import_rerun

    rr = import_rerun()

    path = Path(path)
    try:
        arrays, attrs = read_plan(path)
    except (OSError, KeyError, ValueError) as exc:
        raise UserError(f"{path}: unreadable plan file ({type(exc).__name__}); rerun `dsr-bench plan` for its "
                        "task") from exc
    rec = rr.RecordingStream(APP_ID, recording_id=f"plan-{attrs.get('task', path.stem)}")
    if save is not None:
        save = Path(save)
        save.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(save) as tmp:
            try:
                rec.save(tmp, default_blueprint=plan_blueprint())
                log_plan(rec, arrays, attrs)
                rec.flush()
            finally:
                rec.disconnect()
        return save
    if web:
        from urllib.parse import quote

        uri = rec.serve_grpc(grpc_port=grpc_port, default_blueprint=plan_blueprint())
        _SERVING.append(rec)
        rr.serve_web_viewer(web_port=web_port, open_browser=False, connect_to=uri)
        log_plan(rec, arrays, attrs)
        rec.flush()
        return f"http://localhost:{web_port or 9090}/?url={quote(uri, safe='')}"
    rec.spawn(default_blueprint=plan_blueprint())
    log_plan(rec, arrays, attrs)
    rec.flush()
    return None

"""The 2D track's inputs: the front camera's point-cloud image at the network's resolution, and the push
mapped to the image plane.

The push: action [d, row, col] starts at the centre of workspace cell (row, col) (`geometry.pixel_to_world`)
at the push height (PUSH_HEIGHT above the table); that world point is projected with the sequence's front
camera, resized to the network's image (`geometry.resized_camera`), and rounded to the nearest pixel
(u, v), clipped to the image (the front camera sees the whole workspace, so clipping does not happen on
the benchmark's scenes). The direction d is kept as it is: a world direction, which a fixed camera maps
to a fixed image direction the network learns.

Images are subsampled (every `factor`-th pixel from (0, 0)), not averaged, so every input point is a point
the camera saw.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dsr_bench.constants import PUSH_HEIGHT

#: cameras/front fields a 2D-track model reads (and its training reads)
IMAGE_FIELDS = ("cameras/front/points", "cameras/front/mask", "cameras/front/scene_flow_2d")


def action_pixels(actions: np.ndarray, camera, shape: tuple[int, int]) -> np.ndarray:
    """Actions (T, 3) [d, row, col] as (T, 3) int64 [d, v, u]: the push's start point's pixel in an image of
    `shape` (height, width) of `camera` (a `geometry.Camera`, any size)."""
    from dsr_bench.geometry import pixel_to_world, resized_camera

    actions = np.asarray(actions, dtype=np.int64).reshape(-1, 3)
    xy = pixel_to_world(actions[:, 1:])
    world = np.concatenate([xy, np.full((len(xy), 1), PUSH_HEIGHT)], -1)
    uv, _ = resized_camera(camera, *shape).project(world)
    u = np.clip(np.rint(uv[:, 0]), 0, shape[1] - 1).astype(np.int64)
    v = np.clip(np.rint(uv[:, 1]), 0, shape[0] - 1).astype(np.int64)
    return np.stack([actions[:, 0], v, u], -1)


def reduce_sequence(path: Path, factor: int) -> dict[str, np.ndarray]:
    """One sequence at the network's resolution: points (T+1, h, w, 3) float16 world metres (NaN: no
    return), flow (T, h, w, 3) float16 metres in world (x, y, z) components (the file stores (dy, dx, dz)),
    mask (T, h, w) uint8 visible ids, action (T, 3) int16 [d, v, u]."""
    from dsr_bench.dataset.sequence import SequenceReader

    with SequenceReader(path) as seq:
        missing = [name for name in IMAGE_FIELDS if name not in seq]
        if missing:
            from dsr_bench.errors import UserError

            raise UserError(f"{path}: no {missing[0]}; the 2D track needs the front camera's images "
                            "(generate the sequences without --no-images)")
        steps = seq.num_steps
        points = seq.read("cameras/front/points")[: steps + 1, ::factor, ::factor]
        flow = seq.read("cameras/front/scene_flow_2d")[:steps, ::factor, ::factor][..., [1, 0, 2]]
        mask = seq.read("cameras/front/mask")[:steps, ::factor, ::factor]
        h, w = points.shape[1:3]
        action = action_pixels(np.asarray(seq.read("action"))[:steps], seq.camera("front"), (h, w))
    return {"points": points.astype(np.float16), "flow": flow.astype(np.float16), "mask": mask.astype(np.uint8),
            "action": action.astype(np.int16)}


def point_tensors(points: np.ndarray):
    """Points (..., H, W, 3) world metres with NaN -> torch (..., 3, H, W) float32 (0 where NaN) and valid
    (..., 1, H, W) float32."""
    import torch

    pts = torch.from_numpy(np.asarray(points, dtype=np.float32))
    valid = torch.isfinite(pts).all(-1, keepdim=True)
    pts = torch.where(valid, pts, torch.zeros((), dtype=pts.dtype))
    return pts.movedim(-1, -3).contiguous(), valid.movedim(-1, -3).float().contiguous()

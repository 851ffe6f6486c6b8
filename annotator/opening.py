"""What the annotator window does as it opens: a runtime directory for its process where the environment has none
(`ensure_runtime_dir`), and the 3D view as close as shows the whole workspace (`fit_zoom`, `workspace_corners`).
open3d is asked only for its view control's camera (`fit_zoom`); nothing here opens a window.
"""

from __future__ import annotations

import os

import numpy as np

#: The 3D view opens (and V resets it) as close as shows the whole workspace grid, this fraction of its size from
#: its edges, trying open3d zooms from ZOOM_RANGE's start in steps of ZOOM_STEP.
VIEW_MARGIN = 0.03
ZOOM_RANGE = (0.3, 2.0)
ZOOM_STEP = 0.02


def ensure_runtime_dir() -> str | None:
    """Give this process a private XDG_RUNTIME_DIR (a new directory of its own, mode 0700, removed at exit) when
    the environment has none that is valid: set, absolute, a directory of this user's that no one else may enter.
    Returns the directory made, or None when the environment's was kept.

    GLFW (open3d's windows) asks libwayland for a Wayland display first, and libwayland prints "error:
    XDG_RUNTIME_DIR is invalid or not set in the environment." without one (a login without a session manager, a
    container, `xvfb-run`), though the window then opens on X as it should. A directory of the process's own is
    what the XDG base directory specification asks for; no Wayland server is there, so GLFW goes on to X."""
    import atexit
    import shutil
    import stat
    import tempfile

    current = os.environ.get("XDG_RUNTIME_DIR", "")
    if current and os.path.isabs(current):
        try:
            info = os.stat(current)
        except OSError:
            info = None
        if info is not None and stat.S_ISDIR(info.st_mode) and info.st_uid == os.getuid() \
                and not info.st_mode & 0o077 and os.access(current, os.W_OK | os.X_OK):
            return None
    made = tempfile.mkdtemp(prefix="dsr-bench-runtime-")  # 0700, this user's
    os.environ["XDG_RUNTIME_DIR"] = made
    atexit.register(shutil.rmtree, made, True)
    return made


def workspace_corners() -> np.ndarray:
    """The 8 corners (8, 3) m of the workspace grid's box (`dsr_bench.constants.GRID_BOUNDS`, table frame)."""
    from dsr_bench.constants import GRID_BOUNDS

    return np.array([[x, y, z] for x in GRID_BOUNDS[0] for y in GRID_BOUNDS[1] for z in GRID_BOUNDS[2]])


def fit_zoom(ctr, points: np.ndarray, margin: float = VIEW_MARGIN) -> float:
    """Set an open3d ViewControl's zoom to the closest (of steps of ZOOM_STEP from ZOOM_RANGE's start) at which
    every point (M, 3) m projects inside its view, `margin` of the view's width and height from the edges, and
    return it (the range's end when none fits)."""
    from dsr_bench.annotator.picking import project

    zoom = ZOOM_RANGE[0]
    while zoom < ZOOM_RANGE[1]:
        ctr.set_zoom(zoom)
        params = ctr.convert_to_pinhole_camera_parameters()
        w, h = params.intrinsic.width, params.intrinsic.height
        uv, z = project(points, params.intrinsic.intrinsic_matrix, params.extrinsic)
        if np.all(z > 0) and np.all((uv >= margin * np.array([w, h])) & (uv <= (1 - margin) * np.array([w, h]))):
            return zoom
        zoom += ZOOM_STEP
    ctr.set_zoom(ZOOM_RANGE[1])
    return ZOOM_RANGE[1]

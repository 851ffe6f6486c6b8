"""Plain helpers shared by test modules (fixtures live in conftest.py)."""

import numpy as np

from dsr_bench.geometry import pose_to_matrix


def place_from_truth(session, truth, step: int = 0, snap: bool = True) -> None:
    """Initialise every object of an annotator Session at `step` from 4 picked pairs on its true pose (as a
    user's picks would), then snap it (ICP) unless `snap` is False."""
    for i in range(session.num_objects):
        v, _ = session.capture.mesh(i)
        idx = np.linspace(0, len(v) - 1, 4).astype(int)
        m = pose_to_matrix(truth[step, i])
        session.init_from_picks(i, v[idx], v[idx] @ m[:3, :3].T + m[:3, 3])
        if snap:
            session.snap(i)

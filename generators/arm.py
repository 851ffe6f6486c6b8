"""The authors' UR5 push, computed: the joint-space path of each move and the tool pose it carries.

The arm itself is never simulated (it stays out of the physics and out of view); only its tool is,
held to the flange pose computed here at every physics step. The model is the one measured from
the authors' unmodified simulator (`official-push-trajectories.h5` and its page in the shared
reference data), where it reproduces the recorded tool tip to 0.1 mm:

- Inverse kinematics in closed form: the tool points straight down, wrist 2 at -pi/2, wrist 1
  keeping the flange level (q3 = -pi/2 - q1 - q2), wrist 3 = wrap(q0 + pi), elbow branch q2 >= 0.
- Joint motion: every physics step, q <- q + gain * (q_target - q), a straight line in joint
  space with an exponential time law; a move ends `latency` steps after every joint is within
  JOINT_EPSILON of its target (the authors' polling loop notices a few steps late).
- Forward kinematics: the UR5's standard Denavit-Hartenberg chain; the tool tip is TIP_OFFSET along
  the flange's z axis.

Every number is computed with correctly rounded IEEE operations in a fixed order and glibc's
`sin`/`cos`/`atan2`/`acos`/`sqrt` (Python's `math`), never numpy's vectorised transcendental
functions or BLAS, so a path has the same bits on every x86-64 CPU (DATASHEET.md, reproducibility).
Frame: the pybullet world (the robot base at the origin, z up, the table at z = 0); metres, radians.
Joint order: shoulder pan, shoulder lift, elbow, wrist 1, wrist 2, wrist 3.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from dsr_bench.constants import PUSH_APPROACH_HEIGHT, PUSH_HEIGHT, PUSH_LENGTH

#: UR5 Denavit-Hartenberg parameters (standard convention): link offsets d, lengths a (m) and twists
#: alpha, the twists given by their exact cosine and sine.
UR5_D: tuple[float, ...] = (0.089159, 0.0, 0.0, 0.10915, 0.09465, 0.0823)
UR5_A: tuple[float, ...] = (0.0, -0.425, -0.39225, 0.0, 0.0, 0.0)
UR5_ALPHA_COS: tuple[float, ...] = (0.0, 1.0, 1.0, 0.0, 0.0, 1.0)
UR5_ALPHA_SIN: tuple[float, ...] = (1.0, 0.0, 0.0, 1.0, -1.0, 0.0)
#: The tool tip's distance along the flange's z axis (m): the link the authors' IK targets.
TIP_OFFSET: float = 0.145
#: The arm's rest configuration between pushes (rad), the authors' home.
HOME_Q: tuple[float, ...] = (-3.186603833231106, -2.7046623323544323, 1.9797780717750348,
                             -0.8458013020952369, -1.5941890970134802, -0.04501555880643846)
#: A move has arrived when every joint is within this of its target (rad).
JOINT_EPSILON: float = 0.01


class Phase(IntEnum):
    """The moves of one push, in order."""

    APPROACH = 0  # from home to PUSH_APPROACH_HEIGHT above the start
    DESCEND = 1  # down to PUSH_HEIGHT
    PUSH = 2  # along the push direction for PUSH_LENGTH (commanded)
    LIFT = 3  # up to PUSH_APPROACH_HEIGHT above the commanded end
    HOME = 4  # back to HOME_Q (a joint target)


#: The joint law's gain of each move (fraction of the remaining joint error closed per physics step).
PHASE_GAINS: tuple[float, ...] = (0.05, 0.1, 0.005, 0.005, 0.1)
#: Physics steps between a move's arrival and the next move's start: the recording's typical polling
#: latencies (medians over 180 pushes: 6 6 6 6 5; 7 for the approach as the reference model uses). Fixed,
#: so the generator is deterministic; the recorded latencies move the tip by 0.3 mm on average.
PHASE_LATENCY: tuple[int, ...] = (7, 6, 6, 6, 5)
#: A move that has not arrived after this many steps is a bug in the path (the authors' 5 s timeout
#: at 240 Hz, which no recorded move reached).
MAX_MOVE_STEPS: int = 1200


def flange_poses(q: np.ndarray) -> np.ndarray:
    """Flange poses (n, 4, 4), world frame, of joint angles q (n, 6) in radians."""
    q = np.asarray(q, dtype=np.float64).reshape(-1, 6)
    n = len(q)
    pose = np.zeros((n, 4, 4))
    pose[:, 0, 0] = pose[:, 1, 1] = pose[:, 2, 2] = pose[:, 3, 3] = 1.0
    for j in range(6):
        cos = np.array([math.cos(v) for v in q[:, j]])
        sin = np.array([math.sin(v) for v in q[:, j]])
        ca, sa = UR5_ALPHA_COS[j], UR5_ALPHA_SIN[j]
        link = np.zeros((n, 4, 4))
        link[:, 0, 0], link[:, 0, 1], link[:, 0, 2], link[:, 0, 3] = cos, -sin * ca, sin * sa, UR5_A[j] * cos
        link[:, 1, 0], link[:, 1, 1], link[:, 1, 2], link[:, 1, 3] = sin, cos * ca, -cos * sa, UR5_A[j] * sin
        link[:, 2, 1], link[:, 2, 2], link[:, 2, 3] = sa, ca, UR5_D[j]
        link[:, 3, 3] = 1.0
        pose = _compose(pose, link)
    return pose


def _compose(left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """Products of (n, 4, 4) transforms, summed term by term in a fixed order (no BLAS)."""
    out = np.empty_like(left)
    for r in range(4):
        for c in range(4):
            out[:, r, c] = (left[:, r, 0] * right[:, 0, c] + left[:, r, 1] * right[:, 1, c]
                            + left[:, r, 2] * right[:, 2, c] + left[:, r, 3] * right[:, 3, c])
    return out


def tool_tips(q: np.ndarray) -> np.ndarray:
    """Tool tip positions (n, 3), world metres, of joint angles q (n, 6)."""
    return tips_of_flanges(flange_poses(q))


def tips_of_flanges(flange: np.ndarray) -> np.ndarray:
    """Tool tip positions (n, 3), world metres, of flange poses (n, 4, 4): TIP_OFFSET along each flange's z."""
    return flange[:, :3, 3] + TIP_OFFSET * flange[:, :3, 2]


def rotation_quaternions(rotation: np.ndarray) -> np.ndarray:
    """Unit quaternions (n, 4) as (x, y, z, w), w >= 0, of rotation matrices (n, 3, 3) (Shepperd's method:
    each from its largest of w, x, y, z, so none loses precision)."""
    r = np.asarray(rotation, dtype=np.float64).reshape(-1, 3, 3)
    d0, d1, d2 = r[:, 0, 0], r[:, 1, 1], r[:, 2, 2]
    candidates = np.stack([1.0 + d0 - d1 - d2, 1.0 - d0 + d1 - d2, 1.0 - d0 - d1 + d2, 1.0 + d0 + d1 + d2], 1)
    largest = np.argmax(candidates, axis=1)
    root = np.sqrt(np.take_along_axis(candidates, largest[:, None], 1)[:, 0])  # 2 |component|
    half = 0.5 / root
    zy, yz, xz, zx, yx, xy = r[:, 2, 1], r[:, 1, 2], r[:, 0, 2], r[:, 2, 0], r[:, 1, 0], r[:, 0, 1]
    rows = {  # (x, y, z, w) * 2 |component| for each choice of the largest component
        0: (root * root, xy + yx, xz + zx, zy - yz),
        1: (xy + yx, root * root, yz + zy, xz - zx),
        2: (xz + zx, yz + zy, root * root, yx - xy),
        3: (zy - yz, xz - zx, yx - xy, root * root),
    }
    out = np.empty((len(r), 4))
    for choice, row in rows.items():
        pick = largest == choice
        out[pick] = np.stack([v[pick] for v in row], 1) * half[pick, None]
    return np.where(out[:, 3:] < 0.0, -out, out)


def rotation_vectors(to: np.ndarray, frm: np.ndarray) -> np.ndarray:
    """Rotation vectors (n, 3), world frame (axis times angle, rad), that turn unit quaternions `frm` (n, 4)
    into `to` (n, 4), both (x, y, z, w)."""
    to, frm = np.asarray(to, np.float64).reshape(-1, 4), np.asarray(frm, np.float64).reshape(-1, 4)
    x1, y1, z1, w1 = to.T
    x0, y0, z0, w0 = -frm[:, 0], -frm[:, 1], -frm[:, 2], frm[:, 3]  # the conjugate of frm
    rel = np.stack([w1 * x0 + x1 * w0 + y1 * z0 - z1 * y0, w1 * y0 - x1 * z0 + y1 * w0 + z1 * x0,
                    w1 * z0 + x1 * y0 - y1 * x0 + z1 * w0, w1 * w0 - x1 * x0 - y1 * y0 - z1 * z0], 1)
    rel = np.where(rel[:, 3:] < 0.0, -rel, rel)
    sine = np.sqrt(rel[:, 0] * rel[:, 0] + rel[:, 1] * rel[:, 1] + rel[:, 2] * rel[:, 2])
    angle = np.array([2.0 * math.atan2(s, w) for s, w in zip(sine, rel[:, 3])])
    scale = np.divide(angle, sine, out=np.full_like(angle, 2.0), where=sine > 0.0)
    return rel[:, :3] * scale[:, None]


def inverse_kinematics(tip: np.ndarray, base_angle: float) -> np.ndarray:
    """Joint angles (6,) that put the tool tip at `tip` (3,) (world metres) pointing straight down,
    with the shoulder pan chosen nearest to `base_angle` (rad). A point beyond reach gets the arm
    stretched towards it (elbow 0), as the authors' IK does."""
    x, y, z = (float(v) for v in tip)
    wrist_offset = UR5_D[3]
    reach = max(math.sqrt(x * x + y * y), wrist_offset)
    along = -math.sqrt(reach * reach - wrist_offset * wrist_offset)  # the elbow side facing the table
    pan = math.atan2(y, x) - math.atan2(-wrist_offset, along)
    pan += 2.0 * math.pi * round((base_angle - pan) / (2.0 * math.pi))
    # the planar shoulder-elbow chain: 0.425 (cos q1, sin q1) + 0.39225 (cos q12, sin q12) = (u, w)
    u = -(along + UR5_D[4])
    w = -(z - UR5_D[0] + UR5_D[5] + TIP_OFFSET)
    upper, fore = -UR5_A[1], -UR5_A[2]
    cos_elbow = (u * u + w * w - upper * upper - fore * fore) / (2.0 * upper * fore)
    elbow = math.acos(min(1.0, max(-1.0, cos_elbow)))
    shoulder = math.atan2(w, u) - math.atan2(fore * math.sin(elbow), upper + fore * math.cos(elbow))
    wrist_3 = pan + math.pi
    wrist_3 = (wrist_3 + math.pi) % (2.0 * math.pi) - math.pi
    return np.array([pan, shoulder, elbow, -0.5 * math.pi - shoulder - elbow, -0.5 * math.pi, wrist_3])


def joint_move(q_start: np.ndarray, q_target: np.ndarray, gain: float, latency: int,
               steps: int | None = None) -> np.ndarray:
    """The joint angles (n, 6) after each physics step of one move from `q_start` towards `q_target`:
    the exponential law until every joint is within JOINT_EPSILON of its target, then `latency` more
    steps of it; or exactly `steps` steps of it when given (a recorded move's length)."""
    q = np.array(q_start, dtype=np.float64)
    target = np.asarray(q_target, dtype=np.float64)
    states = []
    end = steps
    for k in range(1, MAX_MOVE_STEPS + latency + 1 if steps is None else steps + 1):
        q = q + gain * (target - q)
        states.append(q)
        if end is None and np.abs(target - q).max() < JOINT_EPSILON:
            end = k + latency
        if k == end:
            return np.array(states)
    raise RuntimeError(f"joint_move: no arrival within {MAX_MOVE_STEPS} steps (gain {gain}); the target is unreachable")


@dataclass(frozen=True)
class PushPath:
    """The arm's path through one push, one row per physics step (the state after that step).

    q: (n, 6) joint angles (rad); phase: (n,) the Phase of each step; flange: (n, 4, 4) flange poses
    (world); tip: (n, 3) tool tip positions (world metres)."""

    q: np.ndarray
    phase: np.ndarray
    flange: np.ndarray
    tip: np.ndarray

    def steps(self, phase: Phase) -> np.ndarray:
        """Indices of the steps of one phase."""
        return np.flatnonzero(self.phase == phase)


def push_targets(start: np.ndarray, angle: float, distance: float = PUSH_LENGTH) -> np.ndarray:
    """The four tool-tip targets (4, 3) of a push from `start` (x, y) at `angle` (rad, world xy): above
    the start, at the start, at the end, above the end (world metres)."""
    sx, sy = float(start[0]), float(start[1])
    ex, ey = sx + math.cos(angle) * distance, sy + math.sin(angle) * distance
    return np.array([[sx, sy, PUSH_APPROACH_HEIGHT], [sx, sy, PUSH_HEIGHT], [ex, ey, PUSH_HEIGHT],
                     [ex, ey, PUSH_APPROACH_HEIGHT]])


def push_path(start: np.ndarray, angle: float, distance: float = PUSH_LENGTH,
              latencies: tuple[int, ...] = PHASE_LATENCY, q_home: tuple[float, ...] = HOME_Q,
              move_steps: tuple[int, ...] | None = None) -> PushPath:
    """The arm's path of one push from rest at `q_home`: approach, descend, push `distance` from `start`
    (x, y; world metres) at `angle` (rad, world xy, the authors' direction d * pi / 4), lift, home.
    Each move lasts until arrival plus its latency, or `move_steps` (one count per move) when given."""
    q = np.array(q_home, dtype=np.float64)
    moves, phases = [], []
    targets = push_targets(start, angle, distance)
    for phase in Phase:
        target = np.array(q_home) if phase == Phase.HOME else inverse_kinematics(targets[phase], q[0])
        move = joint_move(q, target, PHASE_GAINS[phase], latencies[phase],
                          None if move_steps is None else move_steps[phase])
        moves.append(move)
        phases.append(np.full(len(move), phase, dtype=np.int8))
        q = move[-1]
    q_all = np.concatenate(moves)
    flange = flange_poses(q_all)
    return PushPath(q=q_all, phase=np.concatenate(phases), flange=flange, tip=tips_of_flanges(flange))

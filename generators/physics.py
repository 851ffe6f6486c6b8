"""The pybullet world of one sequence: table, objects, the pusher tool, and our own stepping loop.

pybullet runs in DIRECT mode with a fixed time step and is stepped only by this module (no real-time
sleeps, no background thread). A world is built fresh for every sequence and torn down after it, so
results never depend on what ran before.

Dynamics follow the official generator: every object has lateral friction 0.25 and spinning
friction 0.003, the table 1.0 (pybullet multiplies two bodies' frictions: object-table 0.25,
object-object 0.0625); the pusher is a 3 mm stick with friction 1.0 and a friction anchor that
travels PUSH_TRAVEL (as far as the official arm takes it). Scenes are dropped from 0.2 m inside a
fence that is removed after 1 s. What differs (DATASHEET.md, deliberate differences): no arm (the
tool is moved straight by a constraint; the arm is out of view when the camera looks), a small
rolling friction, and the fence is a square of FENCE_HALF_SIZE around the workspace centre (the
official fence's size is not documented; this one gives the official distribution of initial
distances from the centre).
"""

from __future__ import annotations

import numpy as np

from dsr_bench.constants import GRID_BOUNDS, PUSH_HEIGHT, PUSHER_LENGTH, PUSHER_RADIUS
from dsr_bench.geometry import vector_norm

TIME_STEP = 1.0 / 240.0
PUSH_SPEED = 0.25  # m/s along the push (quasi-static at these masses and frictions)
PUSH_HOLD_STEPS = 24  # steps at the push's end point before the tool lifts (it lags its moving target)
SETTLE_LINEAR_SPEED = 5e-3  # m/s
SETTLE_ANGULAR_SPEED = 5e-2  # rad/s
MAX_SETTLE_STEPS = 480
MIN_SETTLE_STEPS = 24
#: Official frictions: objects, the table (pybullet's plane.urdf) and the pusher stick.
OBJECT_FRICTION = 0.25
OBJECT_SPINNING_FRICTION = 0.003
#: Not official (the authors set none): a round object on its side comes to rest within a push (a can
#: set rolling at 0.3 m/s stops after 15 cm) instead of rolling on between observations, in and out of the grid.
OBJECT_ROLLING_FRICTION = 0.002
TABLE_FRICTION = 1.0
PUSHER_FRICTION = 1.0
#: The drop: objects fall inside a fence (walls FENCE_HEIGHT tall around a square of FENCE_HALF_SIZE
#: around the workspace centre) that is removed after FENCE_SECONDS; then the scene settles.
FENCE_HALF_SIZE = 0.2
FENCE_HEIGHT = 0.3
FENCE_SECONDS = 1.0
MAX_DROP_SETTLE_STEPS = 720
_PUSHER_HOME = (0.0, -1.5, 0.5)


def import_pybullet():
    """Import pybullet without the build-time banner its C module prints to stderr."""
    import os
    import sys

    if "pybullet" in sys.modules:
        return sys.modules["pybullet"]
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "w") as devnull:
            os.dup2(devnull.fileno(), 2)
            import pybullet
    finally:
        os.dup2(saved, 2)
        os.close(saved)
    return pybullet


class PushWorld:
    """A pybullet world with the given objects (ObjectSpec-like: `.parts`, `.mass`) on a table."""

    def __init__(self, objects):
        pb = import_pybullet()
        self._pb = pb
        self.client = pb.connect(pb.DIRECT)
        c = self.client
        pb.resetSimulation(physicsClientId=c)
        pb.setPhysicsEngineParameter(fixedTimeStep=TIME_STEP, numSolverIterations=50,
                                     deterministicOverlappingPairs=1, physicsClientId=c)
        pb.setGravity(0, 0, -9.81, physicsClientId=c)
        plane = pb.createCollisionShape(pb.GEOM_PLANE, physicsClientId=c)
        self.table = pb.createMultiBody(0, plane, physicsClientId=c)
        pb.changeDynamics(self.table, -1, lateralFriction=TABLE_FRICTION, physicsClientId=c)
        self.bodies = [self._create_object(obj) for obj in objects]
        tool = pb.createCollisionShape(pb.GEOM_CYLINDER, radius=PUSHER_RADIUS, height=PUSHER_LENGTH,
                                       physicsClientId=c)
        self.pusher = pb.createMultiBody(1.0, tool, basePosition=_PUSHER_HOME, physicsClientId=c)
        pb.changeDynamics(self.pusher, -1, lateralFriction=PUSHER_FRICTION, spinningFriction=PUSHER_FRICTION,
                          frictionAnchor=1, physicsClientId=c)
        self._grip = pb.createConstraint(self.pusher, -1, -1, -1, pb.JOINT_FIXED, [0, 0, 0], [0, 0, 0],
                                         _PUSHER_HOME, physicsClientId=c)
        pb.changeConstraint(self._grip, _PUSHER_HOME, maxForce=500.0, physicsClientId=c)

    def _create_object(self, obj) -> int:
        pb, c = self._pb, self.client
        shapes = [pb.createCollisionShape(pb.GEOM_MESH, vertices=np.asarray(p.vertices, float).tolist(),
                                          physicsClientId=c) for p in obj.parts]
        if len(shapes) == 1:
            body = pb.createMultiBody(obj.mass, shapes[0], basePosition=[0, 0, -1], physicsClientId=c)
        else:  # a compound: every part hull as a fixed link, all frames coincide with the object frame
            n = len(shapes) - 1
            body = pb.createMultiBody(
                obj.mass * 0.5, shapes[0], basePosition=[0, 0, -1],
                linkMasses=[obj.mass * 0.5 / n] * n, linkCollisionShapeIndices=shapes[1:],
                linkVisualShapeIndices=[-1] * n, linkPositions=[[0, 0, 0]] * n,
                linkOrientations=[[0, 0, 0, 1]] * n, linkInertialFramePositions=[[0, 0, 0]] * n,
                linkInertialFrameOrientations=[[0, 0, 0, 1]] * n, linkParentIndices=[0] * n,
                linkJointTypes=[pb.JOINT_FIXED] * n, linkJointAxis=[[0, 0, 1]] * n, physicsClientId=c)
        for link in range(-1, pb.getNumJoints(body, physicsClientId=c)):
            pb.changeDynamics(body, link, lateralFriction=OBJECT_FRICTION, spinningFriction=OBJECT_SPINNING_FRICTION,
                              rollingFriction=OBJECT_ROLLING_FRICTION, physicsClientId=c)
        return body

    def drop(self, poses: np.ndarray) -> int:
        """Place the objects at `poses` (N, 7) (above the table), let them fall inside the fence for
        FENCE_SECONDS, remove the fence and settle; return the settling steps after the fence (-1 if
        an object left the grid while settling)."""
        pb, c = self._pb, self.client
        centre, h, height = np.array([0.5, 0.0]), FENCE_HALF_SIZE, FENCE_HEIGHT
        walls = []
        for axis in (0, 1):
            for side in (-1.0, 1.0):
                half = [0.005, h + 0.005, height / 2] if axis == 0 else [h + 0.005, 0.005, height / 2]
                position = [centre[0], centre[1], height / 2]
                position[axis] += side * (h + 0.005)
                shape = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=half, physicsClientId=c)
                walls.append(pb.createMultiBody(0, shape, basePosition=position, physicsClientId=c))
        for i, pose in enumerate(poses):
            self.set_pose(i, pose)
        self.step(int(round(FENCE_SECONDS / TIME_STEP)))
        for wall in walls:
            pb.removeBody(wall, physicsClientId=c)
        return self.settle(MAX_DROP_SETTLE_STEPS)

    # state -----------------------------------------------------------------------------------------
    def close(self) -> None:
        self._pb.disconnect(physicsClientId=self.client)

    def __enter__(self) -> PushWorld:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def poses(self) -> np.ndarray:
        """Object poses (N, 7) = (x, y, z, qx, qy, qz, qw) in the world frame."""
        out = np.zeros((len(self.bodies), 7))
        for i, body in enumerate(self.bodies):
            pos, orn = self._pb.getBasePositionAndOrientation(body, physicsClientId=self.client)
            out[i, :3], out[i, 3:] = pos, orn
        return out

    def set_pose(self, index: int, pose: np.ndarray) -> None:
        self._pb.resetBasePositionAndOrientation(self.bodies[index], pose[:3], pose[3:], physicsClientId=self.client)
        self._pb.resetBaseVelocity(self.bodies[index], [0, 0, 0], [0, 0, 0], physicsClientId=self.client)

    # stepping --------------------------------------------------------------------------------------
    def step(self, n: int = 1) -> None:
        for _ in range(n):
            self._pb.stepSimulation(physicsClientId=self.client)

    def any_escaped(self) -> bool:
        """Whether some object's centre has left the grid's xy bounds (its hull then has too)."""
        pb, c = self._pb, self.client
        for body in self.bodies:
            x, y, _ = pb.getBasePositionAndOrientation(body, physicsClientId=c)[0]
            if not (GRID_BOUNDS[0, 0] < x < GRID_BOUNDS[0, 1] and GRID_BOUNDS[1, 0] < y < GRID_BOUNDS[1, 1]):
                return True
        return False

    def settle(self, max_steps: int = MAX_SETTLE_STEPS, stop_on_escape: bool = True) -> int:
        """Step until every object is still (or `max_steps`); return the steps taken, or -1 as soon
        as an object has left the grid when `stop_on_escape` (the caller rejects such a scene)."""
        pb, c = self._pb, self.client
        for k in range(1, max_steps + 1):
            pb.stepSimulation(physicsClientId=c)
            if k % 8:
                continue
            if stop_on_escape and self.any_escaped():
                return -1
            if k < MIN_SETTLE_STEPS:
                continue
            still = True
            for body in self.bodies:
                lin, ang = pb.getBaseVelocity(body, physicsClientId=c)
                if vector_norm(lin) > SETTLE_LINEAR_SPEED or vector_norm(ang) > SETTLE_ANGULAR_SPEED:
                    still = False
                    break
            if still:
                return k
        return max_steps

    def push(self, start_xy: np.ndarray, direction_xy: np.ndarray, length: float) -> tuple[np.ndarray, np.ndarray]:
        """Run the push primitive; return the tool tip's start and end points (3,), world metres.

        The tool appears above the start (its approach from 0.15 m runs through free space, which the
        start-point search guarantees), moves straight along `direction_xy` for `length` at
        PUSH_SPEED with its tip at PUSH_HEIGHT, lifts out of the scene, and the objects settle. As in
        the official generator, nothing is undone: a push may move an object out of the grid.
        """
        pb, c = self._pb, self.client
        centre_z = PUSH_HEIGHT + PUSHER_LENGTH / 2
        start = np.array([start_xy[0], start_xy[1], centre_z])
        pb.resetBasePositionAndOrientation(self.pusher, start, [0, 0, 0, 1], physicsClientId=c)
        pb.resetBaseVelocity(self.pusher, [0, 0, 0], [0, 0, 0], physicsClientId=c)
        pb.changeConstraint(self._grip, start.tolist(), maxForce=500.0, physicsClientId=c)
        n = max(1, int(round(length / PUSH_SPEED / TIME_STEP)))
        direction = np.array([direction_xy[0], direction_xy[1], 0.0])
        for k in range(1, n + 1):
            target = start + direction * (length * k / n)
            pb.changeConstraint(self._grip, target.tolist(), maxForce=500.0, physicsClientId=c)
            pb.stepSimulation(physicsClientId=c)
        self.step(PUSH_HOLD_STEPS)  # the tool catches up with its last target: it travels `length`
        tip_end = np.array(pb.getBasePositionAndOrientation(self.pusher, physicsClientId=c)[0])
        pb.resetBasePositionAndOrientation(self.pusher, _PUSHER_HOME, [0, 0, 0, 1], physicsClientId=c)
        pb.resetBaseVelocity(self.pusher, [0, 0, 0], [0, 0, 0], physicsClientId=c)
        pb.changeConstraint(self._grip, _PUSHER_HOME, maxForce=500.0, physicsClientId=c)
        self.settle(stop_on_escape=False)
        offset = np.array([0.0, 0.0, -PUSHER_LENGTH / 2])
        return start + offset, tip_end + offset

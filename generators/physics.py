"""The pybullet world of one sequence: table, objects, the pusher tool, and our own stepping loop.

pybullet runs in DIRECT mode with a fixed time step and is stepped only by this module (no real-time
sleeps, no background thread). A world is built fresh for every sequence, and again at the objects'
rest poses before every push, so a push depends on nothing but the poses it starts from.

Dynamics follow the official generator: every object has lateral friction 0.25 and spinning
friction 0.003, the table 1.0 (pybullet multiplies two bodies' frictions: object-table 0.25,
object-object 0.0625); the table is the box of pybullet's plane.urdf, box parts are box primitives
(the authors' cubes are), other parts convex hulls. The pusher is the authors' stick (a 3 mm x 14 cm
cylinder of 1 g on a 1 g base, frictions 1.0 / 1.0 / 0.0001 with a friction anchor) held by a fixed
constraint of pybullet's default strength to a hand carried along the flange pose of the authors' UR5
at every physics step; the arm's path is computed (`generators.arm`: closed-form IK, joint-space
exponential law, forward kinematics), so the tool moves, slows, bows and lifts as theirs does, and the
arm stays out of the simulation and out of view. Scenes are dropped from 0.2 m inside a fence that is
removed after 1 s. What differs (DATASHEET.md, deliberate differences): no arm body, fixed phase
latencies, no physics while the tool is above every object (nothing can happen then), a fresh world
at rest before every push, a small rolling friction, and the fence is a square of FENCE_HALF_SIZE
around the workspace centre (the official fence's size is not documented; this one gives the official
distribution of initial distances from the centre).

An option for bulk training data (`PushWorld(..., sleep_at_rest=True)`, `dsr-bench generate --sleep-at-rest`):
every object sleeps through the push (Bullet's deactivation: a sleeping body is not simulated) until an awake
body touches it, and sleeps again once it has been still for Bullet's deactivation time. A resting object's
contacts with the table cost the solver more than the rest of a step, so this saves a quarter of a sequence's
CPU time; paired with the same seeds simulated in full, the pushed objects move alike (docs/performance.md).
The pinned splits and planning tasks are made without it: a resting object's jitter is part of their bytes.
"""

from __future__ import annotations

import math

import numpy as np

from dsr_bench.constants import GRID_BOUNDS, NUM_DIRECTIONS, PUSH_HEIGHT, PUSHER_LENGTH, PUSHER_RADIUS
from dsr_bench.geometry import vector_norm
from dsr_bench.generators.arm import Phase, push_path, rotation_quaternions, rotation_vectors

TIME_STEP = 1.0 / 240.0
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
#: The table: the box of pybullet's plane.urdf that the authors load (200 m x 200 m x 10 m, its top at z = 0),
#: so objects rest on a box as theirs do, not on a plane shape (m).
TABLE_HALF_EXTENTS = (100.0, 100.0, 5.0)
#: The authors' stick: a base link and the cylinder link, 1 g each, with the inertias pybullet's URDF
#: importer gives them (kg m^2, principal axes; the cylinder's axis is its z); its frictions.
STICK_LINK_MASS = 0.001
STICK_BASE_INERTIA = (6.666666666666666e-10,) * 3
STICK_INERTIA = (1.7883332618000001e-06, 1.7883332618000001e-06, 2.399999904e-08)
PUSHER_FRICTION = 1.0
PUSHER_SPINNING_FRICTION = 1.0
PUSHER_ROLLING_FRICTION = 0.0001
#: The hold: the stick's centre sits STICK_CENTRE_OFFSET along the flange's z axis, held by a fixed
#: constraint of pybullet's default maximum force (N) to a hand body that carries the flange pose: a soft
#: hold that trails a few mm under load, as the authors' constraint to the arm's link does.
STICK_CENTRE_OFFSET = 0.0725
HOLD_MAX_FORCE = 500.0
#: The hand: a body without a shape, moved along the arm's path with the velocity that reaches the next
#: flange pose in one step (so the hold sees a moving arm, not a pulled anchor); heavy enough that the
#: stick's contacts do not move it within a step (kg). Between pushes a constraint of PARKING_MAX_FORCE (N)
#: holds it at the parking pose.
HAND_MASS = 10.0
PARKING_MAX_FORCE = 1e4
GRAVITY = -9.81
#: Physics runs while the tool tip is below the highest object top plus this (m); above it the tool
#: cannot touch anything and is moved without stepping.
TOOL_CLEARANCE = 0.02
#: The drop: objects fall inside a fence (walls FENCE_HEIGHT tall around a square of FENCE_HALF_SIZE
#: around the workspace centre) that is removed after FENCE_SECONDS; then the scene settles.
FENCE_HALF_SIZE = 0.2
FENCE_HEIGHT = 0.3
FENCE_SECONDS = 1.0
MAX_DROP_SETTLE_STEPS = 720
_TOOL_PARKING = (0.0, -1.5, 0.5)


def box_corners(vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """(centre (3,), half extents (3,)) when the vertices (V, 3) are exactly the 8 corners of an axis-aligned box,
    else None."""
    corners = np.unique(np.asarray(vertices, dtype=np.float64), axis=0)
    if len(corners) != 8:
        return None
    low, high = corners.min(axis=0), corners.max(axis=0)
    if not np.all(high > low) or not np.all((corners == low) | (corners == high)):
        return None
    return (low + high) / 2.0, (high - low) / 2.0


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
    """A pybullet world with the given objects (ObjectSpec-like: `.parts`, `.mass`) on a table.

    Every push starts from a world built afresh with the objects at rest at `rest_poses` (`restart`): no
    velocity, contact or solver state carries over from what happened before. So a push is a function of the
    poses it starts from alone, and the planning track, which starts each push from a task's or its own stored
    poses, moves the objects exactly as the generator did (`generators.planning.SimEnvironment`)."""

    def __init__(self, objects, poses: np.ndarray | None = None, sleep_at_rest: bool = False):
        pb = import_pybullet()
        #: Whether the objects sleep through each push until touched (Bullet's deactivation; see the module).
        self.sleep_at_rest = sleep_at_rest
        self._pb = pb
        self.client = pb.connect(pb.DIRECT)
        self._objects = list(objects)
        #: The poses (N, 7) the objects last came to rest at (or were placed at): where the next push starts.
        self.rest_poses = np.zeros((len(self._objects), 7))
        self._build()
        if poses is not None:
            self.restart(poses)

    def restart(self, poses: np.ndarray) -> None:
        """Build the world afresh with the objects at rest at `poses` (N, 7) = (x, y, z, qx, qy, qz, qw)."""
        self._build()
        for i, pose in enumerate(np.asarray(poses, dtype=np.float64)):
            self.set_pose(i, pose)
        self.rest_poses = np.array(poses, dtype=np.float64)

    def _build(self) -> None:
        """Table, objects (below the table until placed), stick and hand in an emptied simulation."""
        pb, c = self._pb, self.client
        pb.resetSimulation(physicsClientId=c)
        pb.setPhysicsEngineParameter(fixedTimeStep=TIME_STEP, numSolverIterations=50,
                                     deterministicOverlappingPairs=1, physicsClientId=c)
        pb.setGravity(0, 0, GRAVITY, physicsClientId=c)
        slab = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=TABLE_HALF_EXTENTS,
                                       collisionFramePosition=[0, 0, -TABLE_HALF_EXTENTS[2]], physicsClientId=c)
        self.table = pb.createMultiBody(0, slab, physicsClientId=c)
        pb.changeDynamics(self.table, -1, lateralFriction=TABLE_FRICTION, physicsClientId=c)
        self.bodies = [self._create_object(obj) for obj in self._objects]
        self.pusher = self._create_stick()
        self.hand = pb.createMultiBody(HAND_MASS, -1, basePosition=_TOOL_PARKING, physicsClientId=c)
        pb.changeDynamics(self.hand, -1, linearDamping=0.0, angularDamping=0.0, physicsClientId=c)
        self._hold = pb.createConstraint(self.hand, -1, self.pusher, 0, pb.JOINT_FIXED, [0, 0, 0], [0, 0, 0],
                                         [0, 0, -STICK_CENTRE_OFFSET], physicsClientId=c)
        pb.changeConstraint(self._hold, maxForce=HOLD_MAX_FORCE, physicsClientId=c)
        self._parking: int | None = None
        self._park_tool()

    def _create_stick(self) -> int:
        """The pusher: a base link without a shape and the cylinder link fixed to it, at the parking pose."""
        pb, c = self._pb, self.client
        tool = pb.createCollisionShape(pb.GEOM_CYLINDER, radius=PUSHER_RADIUS, height=PUSHER_LENGTH,
                                       physicsClientId=c)
        stick = pb.createMultiBody(
            STICK_LINK_MASS, -1, basePosition=_TOOL_PARKING, linkMasses=[STICK_LINK_MASS],
            linkCollisionShapeIndices=[tool], linkVisualShapeIndices=[-1], linkPositions=[[0, 0, 0]],
            linkOrientations=[[0, 0, 0, 1]], linkInertialFramePositions=[[0, 0, 0]],
            linkInertialFrameOrientations=[[0, 0, 0, 1]], linkParentIndices=[0], linkJointTypes=[pb.JOINT_FIXED],
            linkJointAxis=[[0, 0, 1]], physicsClientId=c)
        pb.changeDynamics(stick, -1, localInertiaDiagonal=STICK_BASE_INERTIA, physicsClientId=c)
        pb.changeDynamics(stick, 0, localInertiaDiagonal=STICK_INERTIA, lateralFriction=PUSHER_FRICTION,
                          spinningFriction=PUSHER_SPINNING_FRICTION, rollingFriction=PUSHER_ROLLING_FRICTION,
                          frictionAnchor=1, physicsClientId=c)
        return stick

    def _create_object(self, obj) -> int:
        pb, c = self._pb, self.client
        shapes = [self._part_shape(np.asarray(p.vertices, float)) for p in obj.parts]
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

    def _part_shape(self, vertices: np.ndarray) -> int:
        """A part's collision shape: pybullet's box primitive when its vertices (V, 3), object frame, are the 8
        corners of an axis-aligned box (as the authors' cubes are boxes, GEOM_BOX), else their convex hull."""
        pb, c = self._pb, self.client
        box = box_corners(vertices)
        if box is not None:
            centre, half = box
            return pb.createCollisionShape(pb.GEOM_BOX, halfExtents=half.tolist(),
                                           collisionFramePosition=centre.tolist(), physicsClientId=c)
        return pb.createCollisionShape(pb.GEOM_MESH, vertices=vertices.tolist(), physicsClientId=c)

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
        settled = self.settle(MAX_DROP_SETTLE_STEPS)
        self.rest_poses = self.poses()
        return settled

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

    def object_top(self) -> float:
        """The highest point of any object's bounding box (m, world z)."""
        pb, c = self._pb, self.client
        top = 0.0
        for body in self.bodies:
            for link in range(-1, pb.getNumJoints(body, physicsClientId=c)):
                top = max(top, pb.getAABB(body, link, physicsClientId=c)[1][2])
        return top

    def _park_tool(self) -> None:
        """Hold the hand and the stick still at the parking pose, out of every camera's view."""
        pb, c = self._pb, self.client
        stick_centre = np.array(_TOOL_PARKING) + np.array([0.0, 0.0, STICK_CENTRE_OFFSET])
        pb.resetBasePositionAndOrientation(self.hand, _TOOL_PARKING, [0, 0, 0, 1], physicsClientId=c)
        pb.resetBasePositionAndOrientation(self.pusher, stick_centre, [0, 0, 0, 1], physicsClientId=c)
        for body in (self.hand, self.pusher):
            pb.resetBaseVelocity(body, [0, 0, 0], [0, 0, 0], physicsClientId=c)
        if self._parking is None:
            self._parking = pb.createConstraint(self.hand, -1, -1, -1, pb.JOINT_FIXED, [0, 0, 0], [0, 0, 0],
                                                _TOOL_PARKING, physicsClientId=c)
            pb.changeConstraint(self._parking, maxForce=PARKING_MAX_FORCE, physicsClientId=c)

    def push(self, start_xy: np.ndarray, direction: int) -> tuple[np.ndarray, np.ndarray]:
        """Run the authors' push primitive from `start_xy` (x, y; world metres) in direction `direction`
        (0..7, angle direction * pi / 4); return the tool tip's commanded start (x, y, PUSH_HEIGHT) and
        where the arm's path ends the push phase (3,), world metres.

        The world is first built afresh at `rest_poses` (`restart`). The tool follows the arm's path
        (`generators.arm.push_path`) from home through approach, descend, push (15 cm commanded, about
        14.6 cm reached), lift and home; physics steps run while the tool tip is within TOOL_CLEARANCE of
        the highest object top (before and after, nothing can be touched), then the tool is parked out of
        view and the objects settle. As in the official
        generator, nothing is undone: a push may move an object out of the grid.
        """
        path = push_path(np.asarray(start_xy, dtype=np.float64), int(direction) * (2.0 * math.pi / NUM_DIRECTIONS))
        self.restart(self.rest_poses)
        low = np.flatnonzero(path.tip[:, 2] < self.object_top() + TOOL_CLEARANCE)
        if len(low):
            self.carry_tool(path.flange[max(int(low[0]) - 1, 0):int(low[-1]) + 1], sleep=self.sleep_at_rest)
        self._park_tool()
        self.settle(stop_on_escape=False)
        self.rest_poses = self.poses()
        start = np.array([float(start_xy[0]), float(start_xy[1]), PUSH_HEIGHT])
        return start, path.tip[path.steps(Phase.PUSH)[-1]].copy()

    def carry_tool(self, flange: np.ndarray, record: bool = False, sleep: bool = False) -> np.ndarray | None:
        """Carry the stick through flange poses (n, 4, 4), world frame, one physics step per pose after the
        first: it starts at rest at the first, and each step takes the hand to the next pose with the
        velocity that reaches it in one step. With `record`, return the stick's lower end (n - 1, 3),
        world metres, after each step. With `sleep`, every object starts the carry asleep (woken when an awake
        body touches it)."""
        pb, c = self._pb, self.client
        pivots = flange[:, :3, 3]
        turns = rotation_quaternions(flange[:, :3, :3])
        if self._parking is not None:  # (a maximum force of 0 does not release a constraint in pybullet)
            pb.removeConstraint(self._parking, physicsClientId=c)
            self._parking = None
        pb.resetBasePositionAndOrientation(self.pusher, pivots[0] + STICK_CENTRE_OFFSET * flange[0, :3, 2], turns[0],
                                           physicsClientId=c)
        pb.resetBaseVelocity(self.pusher, [0, 0, 0], [0, 0, 0], physicsClientId=c)
        fall = np.array([0.0, 0.0, GRAVITY * TIME_STEP])  # what gravity adds to the hand's velocity in a step
        velocities = (pivots[1:] - pivots[:-1]) / TIME_STEP - fall
        spins = rotation_vectors(turns[1:], turns[:-1]) / TIME_STEP
        if sleep:
            for body in self.bodies:
                pb.changeDynamics(body, -1, activationState=pb.ACTIVATION_STATE_ENABLE_SLEEPING, physicsClientId=c)
                pb.changeDynamics(body, -1, activationState=pb.ACTIVATION_STATE_SLEEP, physicsClientId=c)
        ends = []
        for k in range(1, len(pivots)):
            pb.resetBasePositionAndOrientation(self.hand, pivots[k - 1].tolist(), turns[k - 1].tolist(),
                                               physicsClientId=c)
            pb.resetBaseVelocity(self.hand, velocities[k - 1].tolist(), spins[k - 1].tolist(), physicsClientId=c)
            pb.stepSimulation(physicsClientId=c)
            if record:
                position, orientation = pb.getBasePositionAndOrientation(self.pusher, physicsClientId=c)
                axis = np.array(pb.getMatrixFromQuaternion(orientation, physicsClientId=c)).reshape(3, 3)[:, 2]
                ends.append(np.array(position) + 0.5 * PUSHER_LENGTH * axis)
        return np.array(ends).reshape(-1, 3) if record else None

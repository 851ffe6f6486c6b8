"""Objects that nothing moving can reach sit a push out of the physics (`generators.physics.PushWorld`).

A resting object costs pybullet's solver more than the rest of a physics step (its contacts with the table at 50
iterations: 0.056 of 0.066 ms a step with one cube) and, while nothing can touch it, changes nothing but its own
rest jitter. So during a push (`PushWorld.carry_tool(..., sit_out=True)`) every object is taken out of the world,
keeping its rest pose exactly, and put back at rest, at that pose, as soon as a mover can reach it; an object back
in the world that has come to rest where no mover can reach it, and that touches no object staying in the world, is
taken out again at its new pose (so an object leaning on or supporting one that stays is never taken away from it;
objects at rest that touch only each other leave together). Every decision
reads pybullet's bounding boxes, velocities and closest points and compares them with Python floats: the same
bits on every CPU, so the pushes (and the pins) are too.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from dsr_bench.constants import PUSHER_LENGTH

#: Objects nothing moving can reach sit a push out: they are taken out of the world (their pose is their rest pose,
#: exactly) and put back at rest when a moving body (the stick, or an object in the world) comes near. Every
#: REACH_CHECK_STEPS steps each moving body's bounding box is grown by REACH_MARGIN plus REACH_SPEED_FACTOR times
#: the distance it can travel at its speed in the next REACH_CHECK_STEPS steps (the stick: its own speed or the
#: arm's path's, whichever is larger); an object whose box meets a grown box is put back, and so on through chains
#: (an object put back can reach others). A resting object costs the solver two thirds of a step (its contacts with
#: the table at 50 iterations) and, out of reach, changes nothing but its own rest jitter.
REACH_CHECK_STEPS = 4
REACH_MARGIN = 0.01
REACH_SPEED_FACTOR = 2.0
#: An object in the world whose speed (linear plus angular times its half diagonal) is under STILL_SPEED (m/s) at
#: STILL_CHECKS checks in a row is at rest: out of every mover's reach, it sits the rest of the push out.
STILL_SPEED = 1e-3
STILL_CHECKS = 3


@dataclass(frozen=True)
class _Mover:
    """A moving body (one of its links, or -2: all, pybullet's convention) and how far it can reach before the next
    check: `reach` (m) around its shapes, `box` its bounding box grown by that."""

    body: int
    link: int
    reach: float
    box: tuple[list[float], list[float]]


def _boxes_meet(a: tuple[list[float], list[float]], b: tuple[list[float], list[float]]) -> bool:
    """Whether two boxes (low (3,), high (3,)) overlap or touch."""
    (alo, ahi), (blo, bhi) = a, b
    return (alo[0] <= bhi[0] and blo[0] <= ahi[0] and alo[1] <= bhi[1] and blo[1] <= ahi[1]
            and alo[2] <= bhi[2] and blo[2] <= ahi[2])


def path_travel(flange: np.ndarray, steps: int) -> list[float]:
    """For each pose k of a flange path (n, 4, 4): the farthest the stick's two ends (the flange and the tool tip)
    move along the path from pose k within the next `steps` poses (m; summed step lengths, Python floats in a fixed
    order)."""
    ends = (flange[:, :3, 3], flange[:, :3, 3] + PUSHER_LENGTH * flange[:, :3, 2])
    moves = [0.0] * (len(flange) - 1)
    for points in ends:
        d = points[1:] - points[:-1]
        lengths = np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2]).tolist()
        moves = [max(a, b) for a, b in zip(moves, lengths)]
    out = []
    for k in range(len(flange)):
        total = 0.0
        for length in moves[k:k + steps]:
            total += length
        out.append(total)
    return out


class SittingOut:
    """What `PushWorld` needs to let objects sit a push out (a mixin: the world's bodies, shapes, rest poses and
    object creation are `PushWorld`'s)."""

    time_step: float
    _pb: Any  # the pybullet module
    client: int
    pusher: int
    bodies: list[int | None]
    rest_poses: np.ndarray
    _shapes: list[list[int]]
    _rest_boxes: list[tuple[list[float], list[float]]]
    _still: list[int]

    def _box(self, body: int, link: int | None = None) -> tuple[list[float], list[float]]:
        raise NotImplementedError

    def _create_object(self, index: int) -> int:
        raise NotImplementedError

    def set_pose(self, index: int, pose: np.ndarray) -> None:
        raise NotImplementedError

    def _sit_out(self) -> None:
        """Take every object out of the world (each keeps its rest pose and bounding box); the first
        `_update_sitting_out` puts back those within reach."""
        pb, c = self._pb, self.client
        for i, body in enumerate(self.bodies):
            if body is not None:
                self._rest_boxes[i] = self._box(body)
                pb.removeBody(body, physicsClientId=c)
                self.bodies[i] = None
        self._still = [0] * len(self.bodies)

    def _reach(self, body: int, link: int | None, travel: float) -> tuple[_Mover, bool]:
        """(A body as a mover: how far it can reach before the next check, whether it is still). Its reach:
        REACH_MARGIN plus REACH_SPEED_FACTOR times the larger of `travel` (m) and what its speed covers in
        REACH_CHECK_STEPS steps (linear speed plus angular speed times its box's half diagonal); still: that speed
        under STILL_SPEED."""
        pb, c = self._pb, self.client
        low, high = self._box(body, link)
        lin, ang = pb.getBaseVelocity(body, physicsClientId=c)
        half = [0.5 * (b - a) for a, b in zip(low, high)]
        radius = math.sqrt(half[0] * half[0] + half[1] * half[1] + half[2] * half[2])
        speed = (math.sqrt(lin[0] * lin[0] + lin[1] * lin[1] + lin[2] * lin[2])
                 + math.sqrt(ang[0] * ang[0] + ang[1] * ang[1] + ang[2] * ang[2]) * radius)
        grow = REACH_MARGIN + REACH_SPEED_FACTOR * max(travel, speed * (REACH_CHECK_STEPS * self.time_step))
        return _Mover(body, -2 if link is None else link, grow, ([a - grow for a in low], [b + grow for b in high])), \
            speed < STILL_SPEED

    def _reaches(self, mover: _Mover, index: int, box: tuple[list[float], list[float]]) -> bool:
        """Whether a mover comes within its reach of object `index` (whose bounding box is `box`): in the world,
        or sitting out at its rest pose (its part shapes placed there). The boxes first, then pybullet's closest
        points of the shapes."""
        if not _boxes_meet(mover.box, box):
            return False
        pb, c = self._pb, self.client
        body = self.bodies[index]
        if body is not None:
            return bool(pb.getClosestPoints(mover.body, body, mover.reach, linkIndexA=mover.link, physicsClientId=c))
        pose = self.rest_poses[index].tolist()
        return any(pb.getClosestPoints(mover.body, -1, mover.reach, linkIndexA=mover.link, collisionShapeB=shape,
                                       collisionShapePositionB=pose[:3], collisionShapeOrientationB=pose[3:],
                                       physicsClientId=c)
                   for shape in self._shapes[index])

    def _update_sitting_out(self, tool_travel: float) -> None:
        """Put back at rest (at its rest pose, still) every object sitting out that a mover can reach: the stick
        (whose path moves it `tool_travel` m in the next REACH_CHECK_STEPS steps) or an object in the world that is
        not at rest; the objects put back count as movers in turn. Then take out again every object in the world
        at rest (still at STILL_CHECKS checks in a row) that no mover can reach and that is not within reach of an
        object staying in the world (through chains): its pose becomes its rest pose."""
        pb, c = self._pb, self.client
        movers = [self._reach(self.pusher, 0, tool_travel)[0]]
        resting = []
        for i, body in enumerate(self.bodies):
            if body is None:
                continue
            mover, still = self._reach(body, None, 0.0)
            self._still[i] = self._still[i] + 1 if still else 0
            if self._still[i] >= STILL_CHECKS:
                resting.append(i)
            else:
                movers.append(mover)
        waiting = [i for i, body in enumerate(self.bodies) if body is None]
        new = movers
        while new and waiting:
            reached = [i for i in waiting if any(self._reaches(m, i, self._rest_boxes[i]) for m in new)]
            new = []
            for i in reached:
                body = self.bodies[i] = self._create_object(i)
                self.set_pose(i, self.rest_poses[i])
                self._still[i] = 0
                new.append(self._reach(body, None, 0.0)[0])
                waiting.remove(i)
            movers += new
        boxes = {i: self._box(self.bodies[i]) for i in resting}  # type: ignore[arg-type]
        leaving = [i for i in resting if not any(self._reaches(m, i, boxes[i]) for m in movers)]
        # an object at rest stays while it touches one that stays (its weight or support is part of the scene)
        staying = [self._reach(body, None, 0.0)[0] for i, body in enumerate(self.bodies)
                   if body is not None and i not in leaving]
        while staying and leaving:
            kept = [i for i in leaving if any(self._reaches(m, i, boxes[i]) for m in staying)]
            staying = [self._reach(self.bodies[i], None, 0.0)[0] for i in kept]  # type: ignore[arg-type]
            leaving = [i for i in leaving if i not in kept]
        for i in leaving:
            body = self.bodies[i]
            assert body is not None
            position, orientation = pb.getBasePositionAndOrientation(body, physicsClientId=c)
            self.rest_poses[i, :3], self.rest_poses[i, 3:] = position, orientation
            self._rest_boxes[i] = boxes[i]
            pb.removeBody(body, physicsClientId=c)
            self.bodies[i] = None

"""`--freeze-unreachable`: objects out of every mover's reach sit a push out of the physics (generators.reach).

What must hold: an object nothing can reach keeps its pose bit for bit; an object only a pushed object can reach
is put back in time and is pushed (a chain); the moved objects end where they end with every object simulated,
to a fraction of a millimetre; and the option is recorded in each file, refused with a pinned split, and a
resumed run with other settings is refused.
"""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest

pytest.importorskip("pybullet")

from dsr_bench.generators.objects.primitives import box_solid  # noqa: E402
from dsr_bench.generators.objects.spec import make_spec  # noqa: E402

EDGE = 0.05  # m
#: Pushed along +x from (0.35, 0): A in the tool's path, B only A can reach, C far from both.
POSES = np.array([[0.40, 0.0, EDGE / 2, 0, 0, 0, 1], [0.56, 0.0, EDGE / 2, 0, 0, 0, 1],
                  [0.35, 0.20, EDGE / 2, 0, 0, 0, 1]])


def _cubes() -> list:
    return [make_spec("test", "cube", f"cube_{i}", 1.0, [box_solid([EDGE] * 3, [0, 0, EDGE / 2])],
                      (0.5, 0.5, 0.5), False) for i in range(len(POSES))]


def _push(freeze: bool) -> tuple[np.ndarray, np.ndarray]:
    """(poses after settling at the start, poses after one push along +x from (0.35, 0)), (3, 7) each."""
    from dsr_bench.generators.physics import PushWorld

    with PushWorld(_cubes(), poses=POSES, freeze_unreachable=freeze) as world:
        world.settle()
        world.rest_poses = world.poses()
        before = world.rest_poses.copy()
        world.push(np.array([0.35, 0.0]), 0)
        return before, world.poses()


def test_an_object_out_of_reach_keeps_its_pose_bit_for_bit_and_a_chain_is_pushed_as_with_every_object_simulated():
    before, frozen = _push(freeze=True)
    _, simulated = _push(freeze=False)
    assert _push(freeze=True)[1].tobytes() == frozen.tobytes()  # which objects sit out is decided deterministically
    assert frozen[2].tobytes() == before[2].tobytes()  # C: nothing came near it
    assert frozen[2].tobytes() != simulated[2].tobytes()  # it does jitter when simulated: the test can tell
    moved = np.linalg.norm(frozen[:2, :2] - before[:2, :2], axis=1)
    assert moved[0] > 0.08 and moved[1] > 0.005, moved  # A pushed by the tool, B by A after sitting out
    assert np.abs(frozen[:2, :3] - simulated[:2, :3]).max() < 5e-4  # m


def test_the_option_is_recorded_refused_with_a_split_and_a_resumed_run_must_match(tmp_path, capsys):
    from dsr_bench.cli import main

    out = tmp_path / "data"
    small = ["--objects", "cube", "-n", "1", "--steps", "1", "--out", str(out)]
    assert main(["generate", *small, "--freeze-unreachable"]) == 0
    with h5py.File(out / "seq_0000.h5", "r") as f:
        assert json.loads(f.attrs["generator_args"])["freeze_unreachable"] is True

    capsys.readouterr()
    assert main(["generate", *small]) != 0  # resuming into it without the option: other arguments
    assert "seq_0000.h5" in capsys.readouterr().err

    assert main(["generate", "--split", "cube-test", "--freeze-unreachable", "--out", str(tmp_path / "split")]) != 0
    assert "drop --freeze-unreachable" in capsys.readouterr().err
    assert not (tmp_path / "split").exists()


def test_files_made_without_the_option_do_not_name_it():
    from dsr_bench.generators.episode import EpisodeConfig

    assert "freeze_unreachable" not in EpisodeConfig(objects="cube").as_attrs()
    assert EpisodeConfig(objects="cube", freeze_unreachable=True).as_attrs()["freeze_unreachable"] is True


def test_an_object_touching_one_that_stays_in_the_world_stays_too():
    """B rests against the side of A, out of the stick's reach; while A waits in the world for the stick, B
    stays with it (taking B away would change the forces on A), and with every object out of reach both leave."""
    from dsr_bench.generators.physics import PushWorld

    poses = POSES[:2].copy()
    poses[1, :2] = [0.40, EDGE + 0.001]  # beside A, 1 mm apart
    records = []
    original = PushWorld._update_sitting_out

    def record(world, travel):
        original(world, travel)
        a = world.bodies[0]
        moved = a is not None and np.linalg.norm(
            np.asarray(world._pb.getBasePositionAndOrientation(a, physicsClientId=world.client)[0][:2]) - start) > 1e-3
        records.append((a is not None, world.bodies[1] is not None, moved))

    with PushWorld(_cubes()[:2], poses=poses, freeze_unreachable=True) as world:
        world.settle()
        world.rest_poses = world.poses()
        start = world.rest_poses[0, :2].copy()
        world._update_sitting_out = record.__get__(world)
        world.push(np.array([0.35, 0.0]), 0)
    waiting = [(a, b) for a, b, moved in records if a and not moved]
    assert len(waiting) > 10 and all(b for _, b in waiting), records  # A waited for the stick, and B with it
    assert any(not a and not b for a, b, _ in records)  # out of reach together

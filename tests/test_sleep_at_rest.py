"""`--sleep-at-rest`: every object sleeps through a push (Bullet's deactivation) until an awake body touches it.

What must hold: an object nothing touches is not simulated (it keeps its pose to a few nanometres, where the
simulation moves it by its rest jitter); an object only a pushed object touches is woken and pushed (a chain), and
the moved objects end where they end with every object awake, to a fraction of a millimetre; the same push gives
the same bits; and the option is recorded in each file, refused with a pinned split, and a resumed run with other
settings is refused.
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


def _push(asleep: bool) -> tuple[np.ndarray, np.ndarray]:
    """(poses after settling at the start, poses after one push along +x from (0.35, 0)), (3, 7) each."""
    from dsr_bench.generators.physics import PushWorld

    with PushWorld(_cubes(), poses=POSES, sleep_at_rest=asleep) as world:
        world.settle()
        world.rest_poses = world.poses()
        before = world.rest_poses.copy()
        world.push(np.array([0.35, 0.0]), 0)
        return before, world.poses()


def test_an_untouched_object_is_not_simulated_and_a_chain_is_pushed_as_with_every_object_awake():
    before, asleep = _push(asleep=True)
    _, awake = _push(asleep=False)
    assert _push(asleep=True)[1].tobytes() == asleep.tobytes()  # the same push, the same bits
    still = np.linalg.norm(asleep[2, :3] - before[2, :3])
    jitter = np.linalg.norm(awake[2, :3] - before[2, :3])
    assert still < 5e-8 and jitter > 1e-7, (still, jitter)  # C: asleep, against its rest jitter when awake (m)
    moved = np.linalg.norm(asleep[:2, :2] - before[:2, :2], axis=1)
    assert moved[0] > 0.08 and moved[1] > 0.005, moved  # A pushed by the tool, B woken and pushed by A
    assert np.abs(asleep[:2, :3] - awake[:2, :3]).max() < 2e-4  # m


def test_the_option_is_recorded_refused_with_a_split_and_a_resumed_run_must_match(tmp_path, capsys):
    from dsr_bench.cli import main

    out = tmp_path / "data"
    small = ["--objects", "cube", "-n", "1", "--steps", "1", "--out", str(out)]
    assert main(["generate", *small, "--sleep-at-rest"]) == 0
    with h5py.File(out / "seq_0000.h5", "r") as f:
        assert json.loads(f.attrs["generator_args"])["sleep_at_rest"] is True

    capsys.readouterr()
    assert main(["generate", *small]) != 0  # resuming into it without the option: other arguments
    assert "seq_0000.h5" in capsys.readouterr().err

    assert main(["generate", "--split", "cube-test", "--sleep-at-rest", "--out", str(tmp_path / "split")]) != 0
    assert "drop --sleep-at-rest" in capsys.readouterr().err
    assert not (tmp_path / "split").exists()


def test_files_made_without_the_option_do_not_name_it():
    from dsr_bench.generators.episode import EpisodeConfig

    assert "sleep_at_rest" not in EpisodeConfig(objects="cube").as_attrs()
    assert EpisodeConfig(objects="cube", sleep_at_rest=True).as_attrs()["sleep_at_rest"] is True

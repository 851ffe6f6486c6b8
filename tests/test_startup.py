"""Start-up (issue 20): `dsr-bench --help`, and every command's `--help`, imports none of the heavy libraries,
and a run of boxes or procedural objects imports neither a mesh library nor open3d (whose import pulls in its
plotly/dash viewer). Each check runs the CLI in a fresh interpreter and reads its sys.modules afterwards;
bench/bench_startup.py times the same commands."""

import importlib.util
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "bench"))
import bench_startup  # noqa: E402

#: Not needed to simulate, render and write boxes.
NOT_FOR_BOXES = ("trimesh", "plotly", "dash", "open3d", "scipy", "torch", "rerun")


def test_help_of_every_command_imports_no_heavy_library():
    helps = bench_startup.help_commands(REPO)
    commands = {argv[0] for argv in helps[1:]}
    # the library's commands and those of the entry points (generators, annotator) are all asked
    assert {"generate", "generate-captures", "annotate", "validate", "info", "predict", "evaluate", "view",
            "train"} <= commands
    assert "matplotlib" in bench_startup.HEAVY  # the plots of `evaluate --out` and the leaderboard import it lazily
    report = bench_startup.probe(helps, bench_startup.HEAVY, cwd=REPO)
    assert [r["argv"] for r in report[:-1]] == helps
    for entry in report[:-1]:  # sys.modules only grows: the first argv that names a library imported it
        assert entry["rc"] == 0 and entry["loaded"] == [], entry


def test_probe_sees_what_a_command_imports():
    """The probe reads the interpreter that ran the command: typer (every command needs it) is seen, scipy
    (`--version` does not import it) is not, and the dsr_bench that ran is this checkout's."""
    report = bench_startup.probe([["--version"]], ("typer", "scipy"), cwd=REPO)
    assert report[0] == {"argv": ["--version"], "rc": 0, "loaded": ["typer"]}
    assert Path(report[-1]["dsr_bench"]).parent == REPO / "dsr_bench"


@pytest.mark.skipif(importlib.util.find_spec("pybullet") is None, reason="needs pybullet (the sim extra)")
@pytest.mark.parametrize("objects", ["cube", "procedural"])
def test_a_builtin_run_imports_no_mesh_library_nor_open3d(objects, tmp_path):
    """Boxes, and the procedural mugs, bottles, cans, phones and sofas, are built in numpy alone."""
    out = tmp_path / objects
    run = [*bench_startup.CUBE_RUN, "--out", str(out)]
    run[run.index("cube")] = objects
    report = bench_startup.probe([run], NOT_FOR_BOXES + ("pybullet",), cwd=REPO)
    assert report[0]["rc"] == 0 and (out / "seq_0000.h5").is_file()
    assert report[0]["loaded"] == ["pybullet"]  # it did simulate

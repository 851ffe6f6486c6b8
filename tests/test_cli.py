"""The `dsr-bench` command line: version, help listing every command, usage errors, and the errors a user can fix
(a missing optional extra, a read-only directory) as one line."""

import errno
import os
import subprocess
import sys

import pytest

from dsr_bench import __version__
from dsr_bench.cli import main

COMMANDS = ("generate", "validate", "info", "manifest", "import-official", "predict", "evaluate", "leaderboard",
            "view", "train")


def test_version_and_help(capsys):
    assert main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == __version__
    out = subprocess.run([sys.executable, "-m", "dsr_bench.cli", "--help"], capture_output=True, text=True)
    assert out.returncode == 0 and all(c in out.stdout for c in COMMANDS)


def test_usage_errors_exit_2(capsys):
    assert main(["no-such-command"]) == 2
    assert "No such command" in capsys.readouterr().err
    assert main(["generate", "--objects"]) == 2
    assert "requires an argument" in capsys.readouterr().err


def test_generate_help_says_when_out_is_required(capsys, monkeypatch):
    """--out defaults to data/<split> only with --split; without it generate refuses to start, naming --out."""
    monkeypatch.setenv("COLUMNS", "200")  # one help line per option
    assert main(["generate", "--help"]) == 0
    line = next(x for x in capsys.readouterr().out.splitlines() if "--out" in x)
    assert "Dataset directory (default data/<split> with --split; required otherwise)." in line
    assert main(["generate", "--objects", "cube", "-n", "1"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "--out" in err and "--split" in err


def test_no_display_only_on_linux_without_x11_or_wayland(monkeypatch):
    from dsr_bench.display import no_display

    monkeypatch.setattr(sys, "platform", "linux")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    assert no_display()
    monkeypatch.setenv("DISPLAY", "")
    assert no_display()
    monkeypatch.setenv("DISPLAY", ":0")
    assert not no_display()
    monkeypatch.delenv("DISPLAY")
    monkeypatch.setenv("WAYLAND_DISPLAY", "wayland-0")
    assert not no_display()
    monkeypatch.delenv("WAYLAND_DISPLAY")
    monkeypatch.setattr(sys, "platform", "darwin")
    assert not no_display()


def test_generate_plan_tasks_help_lists_every_task_set(capsys, monkeypatch):
    """The --tasks help of generate-plan-tasks names every task set with its size and objects (from TASK_SETS)."""
    from dsr_bench.planning.tasks import TASK_SETS

    monkeypatch.setenv("COLUMNS", "400")
    assert main(["generate-plan-tasks", "--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "plan-val (50 tasks, procedural objects)" in text
    for spec in TASK_SETS.values():
        assert f"{spec.name} ({spec.num_tasks} tasks, {spec.objects} objects)" in text, spec.name


def _without(modules: tuple[str, ...], argv: list[str], cwd) -> subprocess.CompletedProcess:
    """`dsr-bench ARGV` in a fresh interpreter in which importing each of `modules` fails, as without its extra."""
    code = (f"import sys\nfor m in {modules!r}:\n    sys.modules[m] = None\n"
            f"from dsr_bench.cli import main\nsys.exit(main({argv!r}))\n")
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=cwd)


def _one_line_error(result: subprocess.CompletedProcess) -> str:
    assert result.returncode == 2 and result.stdout == "", (result.returncode, result.stderr[-2000:])
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), result.stderr[-2000:]
    return lines[0]


def test_view_save_without_the_viewer_extra_is_one_line_naming_it(tmp_path):
    """Without rerun, `view --save` ends in one line naming the extra to install, never an ImportError."""
    from dsr_bench.testing import write_synthetic_dataset

    data = write_synthetic_dataset(tmp_path / "data", num_sequences=1, num_steps=1)
    result = _without(("rerun",), ["view", "seq_0000", "--data", str(data), "--save", str(tmp_path / "out.rrd")],
                      tmp_path)
    line = _one_line_error(result)
    assert "rerun" in line and "pip install 'dsr-bench[viewer]'" in line
    assert not (tmp_path / "out.rrd").exists()


def test_challenge_commands_without_the_challenge_extra_are_one_line_naming_it(tmp_path):
    """Without SQLAlchemy `challenge add-team`, without FastAPI `serve`, without httpx `submit`: one line each,
    naming the module and the extra to install."""
    (tmp_path / "pred").mkdir()
    for modules, argv, module in ((("sqlalchemy",), ["challenge", "add-team", str(tmp_path / "ch"), "team"],
                                   "sqlalchemy"),
                                  (("fastapi",), ["serve", str(tmp_path / "ch")], "fastapi"),
                                  (("httpx",), ["submit", str(tmp_path / "pred"), "--server", "http://127.0.0.1:9",
                                                "--token", "t", "--method", "m"], "httpx")):
        line = _one_line_error(_without(modules, argv, tmp_path))
        assert f"needs {module}, which is not installed: pip install 'dsr-bench[challenge]'" in line, line


def test_challenge_create_on_a_read_only_file_system_is_one_line(tmp_path, monkeypatch, capsys):
    """`challenge create RO/ch` where the file system refuses writes (EROFS, simulated: the tests run as root, for whom
    a 0555 directory is writable): one line naming the directory and the reason, nothing made."""
    pytest.importorskip("pybullet")  # `challenge create` comes with the simulator (generators)
    read_only = tmp_path / "ro"
    real_mkdir = os.mkdir

    def mkdir(path, *args, **kwargs):
        if str(path).startswith(str(read_only)):
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(path))
        return real_mkdir(path, *args, **kwargs)

    monkeypatch.setattr(os, "mkdir", mkdir)
    assert main(["challenge", "create", str(read_only / "ch"), "--split", "procedural-novel-mini", "-n", "2"]) == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and err.startswith("error: dsr-bench challenge create: cannot write "), err
    assert str(read_only) in err and os.strerror(errno.EROFS) in err
    assert not read_only.exists()


def test_a_command_plugin_that_cannot_be_imported_is_named_with_the_fix_and_the_rest_still_load(capsys):
    """A source checkout in the working directory shadows the installed package without the `generators` and
    `annotator` packages the install maps into it: their commands are left out with one line naming the plugin,
    the import error, where dsr_bench was imported from and the fix; the other plugins still register."""
    from importlib.metadata import EntryPoint

    from dsr_bench.cli import ENTRY_POINT_GROUP, load_plugin

    missing = EntryPoint(name="annotator", value="dsr_bench.annotator_absent.cli:register", group=ENTRY_POINT_GROUP)
    assert load_plugin(missing) is None
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "dsr_bench.annotator_absent.cli:register" in err and "No module named 'dsr_bench.annotator_absent'" in err
    assert "pip install -e ." in err and "dsr_bench is imported from" in err

    present = EntryPoint(name="annotator", value="dsr_bench.annotator.cli:register", group=ENTRY_POINT_GROUP)
    register = load_plugin(present)
    assert callable(register) and register.__module__ == "dsr_bench.annotator.cli"
    assert capsys.readouterr().err == ""


@pytest.mark.parametrize("option,expected", [(("--workers", "-1"), "--workers -1: give 0 or more"),
                                             (("--keep-free", "-5"), "--keep-free -5: give the free disk to keep")])
def test_serve_options_out_of_range_are_one_line_before_anything_starts(tmp_path, capsys, option, expected):
    pytest.importorskip("fastapi")
    assert main(["serve", str(tmp_path / "no-challenge"), *option]) == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and expected in err, err
    assert not (tmp_path / "no-challenge").exists()

"""The `dsr-bench` command line: version, help listing every command, usage errors."""

import subprocess
import sys

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

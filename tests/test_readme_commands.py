"""Every `dsr-bench` command in the README's bash blocks, as written, where the quickstart leaves a user
(`scripts/quickstart.sh`: the split procedural-novel-mini in data/procedural-novel-mini, its predictions and
results in out/quickstart). The quickstart's data is stood in for by a small synthetic dataset of the same name
and split, pinned for the test as the real one is; each command is one of:

- run: runs as written, in the README's order, and succeeds;
- window: opens the viewer or the annotation window (stubbed here, there is no display), on what it names;
- needs: reads what the quickstart does not make (your ShapeNet copy, the authors' release, a training split,
  the planning tasks, a rig's RealSense cameras): exits 2 with one line naming it and how to get it;
- long: simulates for minutes or runs on a cluster: its arguments are parsed as the command line parses them.

A README command missing from COMMANDS (or one here no longer in the README) fails the test, so each new one is
classed."""

from __future__ import annotations

import os
import re
import shlex
import shutil
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SPLIT = "procedural-novel-mini"
DATA = f"data/{SPLIT}"

#: each README command (as `shlex.split` joins it) -> its kind, and for `needs` what its error line must say
COMMANDS: dict[str, tuple[str, str]] = {
    # What you will type most
    f"dsr-bench view seq_3 --data {DATA}": ("window", f"{DATA}/seq_0003.h5"),
    "dsr-bench evaluate out/quickstart/predictions-dsr": ("run", ""),
    "dsr-bench generate-captures --out captures -n 1": ("long", "simulates a capture; the fixture's stands in"),
    "dsr-bench annotate seq_0": ("window", "captures/seq_0000"),
    "dsr-bench generate --objects shapenet --object-root ~/ShapeNetCore.v2 -n 4000 --out data/shapenet":
        ("needs", "https://shapenet.org"),
    # The commands
    f"dsr-bench generate --split {SPLIT} --out {DATA}": ("long", "the quickstart's own generate"),
    "dsr-bench generate --objects shapenet --object-root ~/ShapeNetCore.v2 -n 4000 --out data/shapenet --workers 8":
        ("needs", "https://shapenet.org"),
    f"dsr-bench validate {DATA}": ("run", ""),
    f"dsr-bench validate {DATA}/seq_0003.h5": ("run", ""),
    f"dsr-bench info {DATA}": ("run", ""),
    f"dsr-bench predict --model static --data {DATA} --split {SPLIT} --out predictions/static": ("run", ""),
    "dsr-bench evaluate predictions/static --out results.json": ("run", ""),
    f"dsr-bench view seq_0003 --data {DATA} --save seq_0003.rrd": ("run", ""),
    "dsr-bench import-official ~/dsr-release/test data/official-test":
        ("needs", "https://github.com/columbia-ai-robotics/dsr"),
    "dsr-bench predict --model dsr --weights ~/dsr-release/pretrained_models/dsr.pth --data data/official-test "
    "--out predictions/dsr-official": ("needs", "weights not found: "),
    f"dsr-bench predict --model dsr --data {DATA} --out predictions/dsr": ("run", ""),
    "dsr-bench train --model dsr --track cpu --data data/cpu-train --out dsr.pt":
        ("needs", "`dsr-bench generate --split cpu-train --out "),
    "dsr-bench train --model dsr --stage cube-single --data data/cube-train --out runs/dsr":
        ("needs", "`dsr-bench generate --split cube-train --out data/cube-train`"),
    "dsr-bench train --model se3net --track cpu --data data/cpu-train --out se3net.pt":
        ("needs", "`dsr-bench generate --split cpu-train --out "),
    "dsr-bench generate-plan-tasks --tasks plan-novel-test --out data/plan-novel-test":
        ("long", "simulates the 100 planning tasks"),
    "dsr-bench plan --model 3dflow --masks observed --tasks plan-novel-test --out plans/3dflow":
        ("needs", "`dsr-bench generate-plan-tasks --tasks plan-novel-test --out data/plan-novel-test`"),
    "dsr-bench generate-captures --out captures -n 5": ("long", "simulates 5 captures"),
    "dsr-bench annotate seq_0000 --captures captures": ("window", "captures/seq_0000"),
    "dsr-bench capture --front 819612070593 --back 819612071104 --robot-file robot.log --out runs/run_07":
        ("needs", "RealSense camera"),
    # Generating data: on a cluster
    "dsr-bench generate --split procedural-train --out /shared/dsr/procedural-train --ray auto": ("long", "Ray"),
    "dsr-bench generate --split procedural-train --out /shared/dsr/procedural-train --slurm --slurm-tasks 64 "
    "--slurm-partition cpu --slurm-time 120 --slurm-logs /shared/dsr/logs": ("long", "SLURM"),
    "dsr-bench generate --split procedural-train --out /shared/dsr/procedural-train --shard ${SLURM_ARRAY_TASK_ID}/64":
        ("long", "a SLURM array"),
}


def readme_commands(text: str) -> list[str]:
    """The `dsr-bench` commands of a Markdown text's bash blocks, in order: continuation lines joined, comments
    dropped, each as its words joined by single spaces."""
    commands = []
    for block in re.findall(r"^ *```bash\n(.*?)^ *```", text, re.M | re.S):
        for line in block.replace("\\\n", " ").splitlines():
            words = shlex.split(line, comments=True)
            if words[:1] == ["dsr-bench"]:
                commands.append(" ".join(words))
    return commands


def test_the_readme_commands_are_the_classed_ones():
    found = readme_commands((ROOT / "README.md").read_text())
    assert sorted(set(found)) == sorted(COMMANDS), "class each README command in COMMANDS"
    assert readme_commands("```bash\ndsr-bench a \\\n  --b c  # note\n# dsr-bench no\nbash x\n```\n") == \
        ["dsr-bench a --b c"]
    _parse(["generate", "--split", SPLIT])
    with pytest.raises(Exception, match="No such option: --no-such-option"):  # what `long` commands are checked for
        _parse(["generate", "--split", SPLIT, "--no-such-option"])


def test_the_quickstart_makes_what_the_readme_reads():
    """The paths the README's commands read are the quickstart's (its variables as it writes them)."""
    script = (ROOT / "scripts" / "quickstart.sh").read_text()
    for made in (f"SPLIT={SPLIT}", "DATA=data/$SPLIT", "OUT=out/quickstart", "for model in oracle static dsr",
                 '--out "$OUT/predictions-$model"', '$B generate --split "$SPLIT" --out "$DATA"'):
        assert made in script, made


@pytest.fixture
def after_quickstart(tmp_path, monkeypatch, capture_dir):
    """A working directory as the quickstart leaves it (a synthetic procedural-novel-mini, pinned; the DSR-Net
    predictions), a capture in captures/seq_0000, an empty home (no ShapeNet, no release), no display."""
    from dsr_bench.cli import main
    from dsr_bench.dataset import splits
    from dsr_bench.dataset.manifest import load_manifest, read_split
    from dsr_bench.dataset.pins import build_pin
    from dsr_bench.testing import write_synthetic_dataset

    work = tmp_path / "work"
    data = write_synthetic_dataset(work / DATA, num_sequences=4, num_steps=1, split=SPLIT)
    pin = build_pin(data, read_split(data, SPLIT)[1], load_manifest(data), SPLIT)
    monkeypatch.setattr(splits, "pinned_digests", lambda: {SPLIT: pin})
    shutil.copytree(capture_dir, work / "captures" / "seq_0000")
    (tmp_path / "home").mkdir()
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    monkeypatch.delenv("DSR_BENCH_SHAPENET", raising=False)
    monkeypatch.setenv("COLUMNS", "200")
    monkeypatch.chdir(work)
    assert main(["predict", "--model", "dsr", "--data", DATA, "--split", SPLIT, "--out",
                 "out/quickstart/predictions-dsr"]) == 0  # the quickstart's, for model dsr
    return work


def _argv(command: str) -> list[str]:
    """The words after `dsr-bench` as a shell gives them: ~ expanded, the SLURM array's task id set."""
    words = command.replace("${SLURM_ARRAY_TASK_ID}", "0").split()[1:]
    return [os.path.expanduser(w) if w.startswith("~") else w for w in words]


def _parse(argv: list[str]) -> None:
    """Parse a command line as `dsr-bench` does, without running it (click's UsageError on a bad one)."""
    import typer

    from dsr_bench.cli import app

    group = typer.main.get_command(app)
    parent = group.context_class(group, info_name="dsr-bench")
    command = group.get_command(parent, argv[0])
    assert command is not None, argv
    command.make_context(argv[0], list(argv[1:]), parent=parent).close()


def test_the_readme_commands_run_as_written_after_the_quickstart(after_quickstart, monkeypatch, capsys):
    import dsr_bench.annotator.window
    import dsr_bench.display
    import dsr_bench.viewer
    from dsr_bench.cli import main

    opened: list[str] = []
    real_view = dsr_bench.viewer.view

    def view(path, **kw):  # a window: record what it shows; a recording: the real viewer
        if kw.get("save") is None and not kw.get("web"):
            return opened.append(str(path))
        return real_view(path, **kw)

    monkeypatch.setattr(dsr_bench.display, "no_display", lambda: False)
    monkeypatch.setattr(dsr_bench.viewer, "view", view)
    monkeypatch.setattr(dsr_bench.annotator.window, "run",
                        lambda session, **options: opened.append(str(session.capture.path)))
    said = {}
    for command in readme_commands((ROOT / "README.md").read_text()):
        kind, expected = COMMANDS[command]
        argv = _argv(command)
        capsys.readouterr()
        if kind == "long":
            _parse(argv)
            continue
        rc = main(argv)
        out, err = said[command] = capsys.readouterr()
        if kind == "needs":
            assert rc == 2 and err.count("\n") == 1 and err.startswith("error: ") and expected in err, (command, err)
            continue
        assert rc == 0, (command, out, err)
        if kind == "window":
            assert opened.pop() == expected, command
    assert opened == []
    assert f"split {SPLIT}: checksum" in said[f"dsr-bench validate {DATA}"].out
    assert f"matches the pinned split {SPLIT}" in said[f"dsr-bench validate {DATA}"].out
    assert "no results JSON" in said["dsr-bench evaluate out/quickstart/predictions-dsr"].err
    for made in ("results.json", "results-steps.png", "seq_0003.rrd", "predictions/static/meta.json",
                 "predictions/dsr/meta.json"):
        assert Path(made).is_file(), made


def test_the_readme_pytorch_example_runs_after_the_quickstart(tmp_path, monkeypatch):
    """The README's PyTorch example (docs/format.md's too) runs as written on the quickstart's split, and its
    loader's two workers deliver a batch and end with it."""
    torch = pytest.importorskip("torch")
    from torch.utils.data import DataLoader

    from dsr_bench.testing import write_synthetic_dataset

    readme = ROOT / "README.md"
    blocks = re.findall(r"^```python\n(.*?)^```", readme.read_text(), re.M | re.S)
    [example] = [b for b in blocks if "SequenceWindowDataset" in b]
    assert example in (ROOT / "docs" / "format.md").read_text()
    write_synthetic_dataset(tmp_path / DATA, num_sequences=1, num_steps=10, split=SPLIT)
    monkeypatch.chdir(tmp_path)
    scope: dict = {}
    exec(compile(example, str(readme), "exec"), scope)
    item, loader = scope["item"], scope["loader"]
    assert isinstance(loader, DataLoader) and loader.num_workers <= 2 and len(scope["ds"]) == 1
    assert item["tsdf"].shape == (10, 128, 128, 48) and item["tsdf"].dtype == torch.float32
    assert item["action"].shape == (10, 8, 128, 128) and item["action"].sum() == 10  # one-hot per push
    assert item["mask_3d"].shape == (10, 128, 128, 48) and item["mask_3d"].dtype == torch.uint8
    assert item["scene_flow_3d"].shape == (10, 3, 128, 128, 48) and item["scene_flow_3d"].dtype == torch.float32
    assert item["sequence"] == "seq_0000" and item["start"] == 0
    [batch] = list(loader)  # through the workers, to the end: they exit with the epoch
    assert torch.equal(batch["mask_3d"][0], item["mask_3d"]) and batch["sequence"] == ["seq_0000"]

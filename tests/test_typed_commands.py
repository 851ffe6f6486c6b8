"""Commands as a user types them: sequence names however padded, the missing options named, what a command did
not write said, a readable command list."""

from __future__ import annotations

from pathlib import Path

import pytest

from dsr_bench.errors import UserError


def test_annotate_finds_a_capture_by_its_number_however_padded(tmp_path):
    """`annotate seq_042`, `annotate 42` and `annotate captures/seq_042` open captures/seq_0042; a number two
    captures share, or one none has, is one line naming what the folder holds."""
    from dsr_bench.annotator.cli import resolve_capture

    captures = tmp_path / "captures"
    for name in ("seq_0000", "seq_0001", "seq_0042"):
        (captures / name).mkdir(parents=True)
    for typed in ("seq_0042", "seq_042", "seq_42", "42"):
        assert resolve_capture(typed, captures) == captures / "seq_0042", typed
    assert resolve_capture(str(captures / "seq_042"), Path("elsewhere")) == captures / "seq_0042"
    with pytest.raises(UserError, match=r"^capture 'seq_7' not found in .*captures: it holds seq_0000..seq_0001, "
                                        r"seq_0042; give one of them or a path \(make simulated ones with "
                                        r"`dsr-bench generate-captures --out .*captures -n 5`\)$"):
        resolve_capture("seq_7", captures)
    (captures / "seq_42").mkdir()
    with pytest.raises(UserError, match="^capture 'seq_042' is ambiguous: seq_0042 and seq_42 both have number 42"):
        resolve_capture("seq_042", captures)
    with pytest.raises(UserError, match=r"capture 'seq_1' not found: no directory .*nowhere; give a capture name"):
        resolve_capture("seq_1", tmp_path / "nowhere")


def test_validate_says_which_pinned_split_the_data_matched(tmp_path, monkeypatch, capsys):
    """A valid dataset's every split is named with its checksum and the pinned split that has it, or none."""
    from dsr_bench.cli import main
    from dsr_bench.dataset import splits
    from dsr_bench.dataset.manifest import load_manifest
    from dsr_bench.dataset.pins import pin_matches
    from dsr_bench.testing import write_synthetic_dataset

    monkeypatch.setenv("COLUMNS", "400")  # rich's lines unwrapped
    data = write_synthetic_dataset(tmp_path / "d", num_sequences=1, num_steps=1, split="test")
    checksum = load_manifest(data)["splits"]["test"]["content_sha256"]
    pinned = len(splits.pinned_digests())
    assert main(["validate", str(data), "--no-gt"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("valid: 1 sequences in")
    assert out[1:] == [f"split test: checksum {checksum}, matches none of the {pinned} pinned splits (not a "
                       "benchmark split)"]
    monkeypatch.setattr(splits, "pinned_digests", lambda: {"cube-test": {"checksum": checksum}})
    assert main(["validate", str(data), "--no-gt"]) == 0
    assert capsys.readouterr().out.splitlines()[1:] == [
        f"split test: checksum {checksum}, matches the pinned split cube-test (its ground truth bit for bit)"]
    manifest = {"splits": {"cube-test": {"content_sha256": "abc"}}}
    assert pin_matches(manifest, {"cube-test": {"checksum": "def"}}) == [
        "split cube-test: checksum abc, matches no pinned split (the pinned cube-test has def)"]
    assert pin_matches({"splits": {}}, {})[0].startswith("no split files: the dataset matches none of the pinned")


def test_the_command_list_has_one_line_per_command(monkeypatch, capsys):
    """`dsr-bench --help` on a wide terminal lists each command on one line: no command's summary breaks where
    its docstring's source line does (typer's rich help keeps those breaks; the CLI reflows every paragraph)."""
    import re

    from dsr_bench.cli import app, main

    monkeypatch.setenv("COLUMNS", "400")
    assert main(["--help"]) == 0
    panel = capsys.readouterr().out.split("Commands", 1)[1].splitlines()[1:]
    rows = panel[:panel.index(next(line for line in panel if line.startswith("╰")))]
    names = [c.name for c in app.registered_commands] + [g.name for g in app.registered_groups]
    assert [re.match(r"│ (\S+)", row).group(1) for row in rows] == names  # one row each, no continuation lines
    groups = [app, *(g.typer_instance for g in app.registered_groups)]
    for command in (c for group in groups for c in group.registered_commands):
        assert command.help and "\n" not in command.help.split("\n\n")[0], command.name  # the summary: one line

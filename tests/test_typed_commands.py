"""Commands as a user types them: sequence names however padded, the missing options named, what a command did
not write said, a readable command list."""

from __future__ import annotations

from pathlib import Path

import pytest

from dsr_bench.errors import UserError


def test_annotate_finds_a_capture_by_its_number_however_padded(tmp_path):
    """`annotate seq_042`, `annotate 42` and `annotate captures/seq_042` open captures/seq_0042; a number two
    captures share, or one none has, is one line naming what the folder holds."""
    from annotator.cli import resolve_capture

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

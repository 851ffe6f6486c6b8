"""The documented contract matches the code: the DATASHEET schema table lists every field as the schema defines it;
the README opens with its two commands, its links resolve (its other commands and its PyTorch example run in
tests/test_readme_commands.py); docs/models.md's `dsr-bench train` commands are ones their tracks take."""

import re
from pathlib import Path

from dsr_bench.dataset.schema import SEQUENCE_SCHEMA

ROOT = Path(__file__).resolve().parents[1]


def test_datasheet_schema_table_matches_schema():
    text = (ROOT / "DATASHEET.md").read_text()
    rows = {m.group(1): m.group(0) for m in re.finditer(r"^\s*\| `([^`]+)` \|.*$", text, re.M)}
    for field in SEQUENCE_SCHEMA:
        name = f"cameras/<cam>/{field.name}" if field.camera else field.name
        assert name in rows, f"DATASHEET.md lacks {name}"
        row = rows[name]
        assert f"({', '.join(field.shape)})" in row and f"| {field.dtype} |" in row, row
        assert field.units in row, row


def test_readme_opens_with_the_two_commands():
    text = (ROOT / "README.md").read_text()
    block = text.split("```bash", 1)[1].split("```", 1)[0].strip().splitlines()
    assert block[0].startswith("bash scripts/quickstart.sh") and block[1].startswith("bash scripts/test.sh")
    assert (ROOT / "scripts" / "quickstart.sh").exists() and (ROOT / "scripts" / "test.sh").exists()
    assert "scripts/test.sh" in (ROOT / ".ci" / "run").read_text()


def _slug(heading: str) -> str:
    """GitHub's anchor of a Markdown heading."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def test_readme_links_the_sources_and_every_link_resolves():
    text = (ROOT / "README.md").read_text()
    for url in ("https://arxiv.org/abs/2011.01791", "https://dsr-net.cs.columbia.edu/",
                "https://github.com/columbia-ai-robotics/dsr", "https://shapenet.org",
                "https://www.ycbbenchmarks.com/", "docs/annotator.md"):
        assert f"]({url})" in text, url
    assert "ShapeNetCore v2" in text and "ShapeNetCore v2" in (ROOT / "docs" / "objects.md").read_text()
    for target in re.findall(r"\]\(([^)]+)\)", text):
        if target.startswith("http"):
            continue
        path, _, anchor = target.partition("#")
        file = ROOT / path if path else ROOT / "README.md"
        assert file.exists(), target
        if anchor:
            headings = re.findall(r"^#+ (.+)$", file.read_text(), re.M)
            assert anchor in {_slug(h) for h in headings}, target


def test_python_m_dsr_bench_is_the_documented_command_line():
    import subprocess
    import sys

    from dsr_bench import __version__

    assert "`python -m dsr_bench`" in (ROOT / "README.md").read_text()
    out = subprocess.run([sys.executable, "-m", "dsr_bench", "--version"], capture_output=True, text=True)
    assert out.returncode == 0 and out.stdout.strip() == __version__


def _bash_commands(path: Path, program: str) -> list[str]:
    """The `program` commands of a Markdown file's bash blocks: continuation lines joined, comments dropped."""
    import shlex

    commands = []
    for block in re.findall(r"^ *```bash\n(.*?)^ *```", path.read_text(), re.M | re.S):
        for line in block.replace("\\\n", " ").splitlines():
            words = shlex.split(line, comments=True)
            if words[:1] == [program]:
                commands.append(" ".join(words))
    return commands


def test_the_documented_train_commands_are_accepted_by_their_tracks(monkeypatch):
    """Every `dsr-bench train` command of docs/models.md (the one-GPU curriculum, the lent-GPU budget, the CPU and 2D
    tracks) parses, and its track reads every option it gives; the recipes are stubbed (nothing trains)."""
    import dsr_bench.cli.train as train_cli
    from dsr_bench.cli import main
    from dsr_bench.models.training.tracks import Track

    ran = []
    monkeypatch.setattr(Track, "train", lambda self, model, options, report: ran.append((model, self.name)) or Path())
    monkeypatch.setattr(train_cli, "_check_heldout", lambda *args: None)
    monkeypatch.setattr(train_cli, "_evaluate", lambda *args: None)
    commands = [c for c in _bash_commands(ROOT / "docs" / "models.md", "dsr-bench") if c.startswith("dsr-bench train ")
                and "..." not in c]
    assert any("--stage curriculum" in c and "--stage-data shapenet-multi=" in c for c in commands)
    assert any("--stage curriculum" in c and "--max-minutes" in c for c in commands)
    for command in commands:
        assert main(command.split()[1:]) == 0, command
    assert {track for _, track in ran} == {"full", "cpu"} and len(ran) == len(commands)

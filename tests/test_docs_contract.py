"""The documented contract matches the code: the DATASHEET schema table lists every field as the schema defines it;
the README opens with its two commands, its PyTorch example runs, its links resolve."""

import re
from pathlib import Path

import pytest

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


def _code_blocks(text: str, language: str) -> list[str]:
    return re.findall(rf"^```{language}\n(.*?)^```", text, re.M | re.S)


@pytest.mark.filterwarnings("ignore:This DataLoader will create")  # the example's 4 workers; none is started
def test_readme_pytorch_example_runs_as_written(tmp_path, monkeypatch):
    """The README's PyTorch example is docs/format.md's, and runs against the real API on a small dataset laid
    out as it says (data/cube-train, split cube-train), giving the shapes its comments state."""
    pytest.importorskip("torch")
    from torch.utils.data import DataLoader

    from dsr_bench.testing import write_synthetic_dataset

    readme = ROOT / "README.md"
    [example] = [b for b in _code_blocks(readme.read_text(), "python") if "SequenceWindowDataset" in b]
    assert example in _code_blocks((ROOT / "docs" / "format.md").read_text(), "python")
    write_synthetic_dataset(tmp_path / "data" / "cube-train", num_sequences=1, num_steps=10, split="cube-train")
    monkeypatch.chdir(tmp_path)
    scope: dict = {}
    exec(compile(example, str(readme), "exec"), scope)
    item, loader = scope["item"], scope["loader"]
    assert isinstance(loader, DataLoader) and loader.batch_size == 12 and len(scope["ds"]) == 1
    assert item["tsdf"].shape == (10, 128, 128, 48) and str(item["tsdf"].dtype) == "torch.float32"
    assert item["action"].shape == (10, 8, 128, 128) and item["action"].sum() == 10  # one-hot per push
    assert item["mask_3d"].shape == (10, 128, 128, 48) and str(item["mask_3d"].dtype) == "torch.uint8"
    assert item["scene_flow_3d"].shape == (10, 3, 128, 128, 48) and str(item["scene_flow_3d"].dtype) == "torch.float32"
    assert item["sequence"] == "seq_0000" and item["start"] == 0


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

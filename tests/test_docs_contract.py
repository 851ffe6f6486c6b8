"""The documented contract matches the code: the DATASHEET schema table lists every field as the schema defines it."""

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

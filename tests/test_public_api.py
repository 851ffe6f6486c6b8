"""The public API (issue 45): `dsr_bench` exports what a user of the library needs, each name imported from its
own module on first use (PEP 562), so that `import dsr_bench` stays light; the docs' examples import from it."""

import ast
import importlib
import importlib.util
import re
import subprocess
import sys
from pathlib import Path

import pytest

import dsr_bench

ROOT = Path(__file__).resolve().parents[1]

#: The public API, pinned: a name added, renamed or removed is a change of the contract (the module's docstring,
#: CONTRIBUTING.md and the docs' examples change with it).
PUBLIC = [
    "__version__", "UserError",
    "SequenceReader", "write_sequence", "validate_sequence", "validate_dataset",
    "SPLITS", "Split", "get_split",
    "write_predictions", "evaluate", "Evaluation",
    "load_predictor", "Predictor", "SequenceWindowDataset", "OfficialWindowDataset",
    "view",
    "verify_tasks", "recompute_results",
]
#: names whose module imports torch at its top
NEEDS_TORCH = {"SequenceWindowDataset", "OfficialWindowDataset"}


def test_the_public_api_is_pinned():
    assert dsr_bench.__all__ == PUBLIC
    assert set(PUBLIC) == {"__version__", *dsr_bench._HOMES}  # each name knows its module, and only those
    assert set(PUBLIC) <= set(dir(dsr_bench))
    for name in PUBLIC[1:]:  # the module's docstring names each one
        assert f"`{name}`" in dsr_bench.__doc__, name


@pytest.mark.parametrize("name", PUBLIC[1:])
def test_each_public_name_is_its_home_modules_object(name):
    if name in NEEDS_TORCH and importlib.util.find_spec("torch") is None:
        pytest.skip("needs torch")
    home = importlib.import_module(dsr_bench._HOMES[name])
    assert getattr(dsr_bench, name) is getattr(home, name)
    namespace: dict = {}
    exec(f"from dsr_bench import {name}", namespace)
    assert namespace[name] is getattr(home, name)


def test_an_unknown_name_is_an_attribute_error():
    with pytest.raises(AttributeError, match="no attribute 'read_sequence'"):
        dsr_bench.read_sequence  # noqa: B018 - the lookup is the test
    assert isinstance(dsr_bench.__version__, str) and dsr_bench.__version__


def test_importing_the_package_imports_none_of_its_modules():
    """`import dsr_bench` loads no module of the library, nor numpy, h5py or torch: a name's module is imported
    when the name is first used, and only that module (with what it imports)."""
    probe = ("import sys, dsr_bench; first = sorted(m for m in sys.modules if m.split('.')[0] in "
             "('dsr_bench', 'numpy', 'h5py', 'torch')); dsr_bench.get_split; "
             "print(first, 'dsr_bench.dataset.splits' in sys.modules, 'dsr_bench.scoring' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, cwd=ROOT, check=True)
    assert out.stdout.split() == ["['dsr_bench']", "True", "False"]


def _python_blocks(text: str) -> list[str]:
    return re.findall(r"```python\n(.*?)```", text, flags=re.S)


def _doc_imports() -> list[tuple[str, str, str]]:
    """(document, module, name) of every `from dsr_bench... import name` in the docs' Python examples."""
    found = []
    for doc in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        for block in _python_blocks(doc.read_text()):  # some are fragments (a table's entry): read line by line
            for line in re.findall(r"^\s*(from dsr_bench[\w.]* import [^(\n]+)$", block, flags=re.M):
                node = ast.parse(line).body[0]
                assert isinstance(node, ast.ImportFrom) and node.module
                found += [(doc.name, node.module, alias.name) for alias in node.names]
    return found


def test_the_docs_examples_import_the_public_api_from_the_package():
    imports = _doc_imports()
    public = [(doc, name) for doc, module, name in imports if module == "dsr_bench"]
    assert {"SequenceReader", "write_predictions", "SequenceWindowDataset", "view"} <= {n for _, n in public}
    assert {doc for doc, _ in public} >= {"README.md", "evaluation.md", "format.md", "viewer.md"}
    assert [(doc, name) for doc, name in public if name not in PUBLIC] == []
    deep = [(doc, f"{module}.{name}") for doc, module, name in imports if module != "dsr_bench" and name in PUBLIC]
    assert deep == []  # a public name is imported from dsr_bench, never from where it lives


def _slug(heading: str) -> str:
    """GitHub's anchor of a Markdown heading."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def test_contributing_states_the_api_is_linked_and_its_links_resolve():
    text = (ROOT / "CONTRIBUTING.md").read_text()
    assert all(f"`{name}`" in text for name in PUBLIC)
    for doc in ("README.md", "DEVELOPERS.md"):
        assert "](CONTRIBUTING.md)" in (ROOT / doc).read_text(), doc
    targets = [t for t in re.findall(r"\]\(([^)]+)\)", text) if not t.startswith("http")]
    assert "docs/models.md#adding-a-model" in targets
    for target in targets:
        path, _, anchor = target.partition("#")
        assert (ROOT / path).exists(), target
        if anchor:
            assert anchor in {_slug(h) for h in re.findall(r"^#+ (.+)$", (ROOT / path).read_text(), re.M)}, target

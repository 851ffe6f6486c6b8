"""The library's parts depend on each other one way: no cycle among dsr_bench's packages and top-level modules,
counting imports inside functions too (they hide the graph from readers, not from this test)."""

import ast
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _part(module: str) -> str | None:
    """The part of dsr_bench a module belongs to: its package or top-level module (dsr_bench.scoring.metrics ->
    scoring), None for the package root."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[0] == "dsr_bench" else None


def _dataset_module(module: str) -> str | None:
    """The module of the dataset package a module is (dsr_bench.dataset.scored -> scored), None for any other."""
    parts = module.split(".")
    return parts[2] if len(parts) > 2 and parts[:2] == ["dsr_bench", "dataset"] else None


def _imported(path: Path) -> list[str]:
    """Every module of dsr_bench a file imports, at its top or inside a function (`from dsr_bench import name`:
    dsr_bench.name, and `from package import module`: package.module)."""
    targets = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] == "dsr_bench":
            package = ROOT / Path(*node.module.split("."))
            targets += [f"{node.module}.{a.name}" if node.module == "dsr_bench" or (package / f"{a.name}.py").is_file()
                        or (package / a.name / "__init__.py").is_file() else node.module for a in node.names]
        elif isinstance(node, ast.Import):
            targets += [a.name for a in node.names]
    return targets


def import_graph(part=_part, root: str = "dsr_bench") -> dict[str, set[str]]:
    """{part: the other parts it imports}, over every module under `root` (a folder of the repository); `part`
    names what a module belongs to (None: not counted)."""
    edges: dict[str, set[str]] = defaultdict(set)
    for path in (ROOT / root).rglob("*.py"):
        me = part(".".join(path.relative_to(ROOT).with_suffix("").parts))
        for target in _imported(path):
            other = part(target)
            if other is not None and me is not None and other != me and other != "__version__":
                edges[me].add(other)
    return edges


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """Every strongly connected group of more than one part (Tarjan), each sorted."""
    index, low, stack, on_stack, found, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in sorted(edges.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                group.append(w)
                if w == v:
                    break
            if len(group) > 1:
                found.append(sorted(group))

    for v in sorted(set(edges) | {w for ws in edges.values() for w in ws}):
        if v not in index:
            visit(v)
    return found


def test_the_library_parts_import_each_other_without_a_cycle():
    edges = import_graph()
    assert "scoring" in edges and "leaderboard" in edges  # the graph was read
    assert cycles(edges) == []
    assert not edges.get("scoring", set()) & {"leaderboard", "models", "planning", "viewer", "cli"}
    top = ("cli", "leaderboard", "challenge", "__main__")  # the command line, the leaderboard, the challenge server
    below = set().union(*(edges[p] for p in edges if p not in top))
    assert not set(top) & below  # sit on top: nothing of the library below them imports them
    assert "challenge" not in edges.get("leaderboard", set())  # the server uses the leaderboard, not the reverse


def test_the_dataset_packages_modules_import_each_other_without_a_cycle():
    """Inside the dataset package too: the storage layer knows nothing of scoring (`nonzero_rows` and
    `le_contiguous` live in `arraybytes`, below both), and the digests read no file (`sequence` reads a file's)."""
    edges = import_graph(_dataset_module, "dsr_bench/dataset")
    assert {"digests", "sequence", "storage", "scored"} <= set(edges)  # the graph was read
    assert cycles(edges) == []
    assert edges["storage"] == {"arraybytes"} and "scored" not in edges["sequence"]


def test_the_library_imports_its_own_modules_never_the_public_facade():
    """`dsr_bench/__init__` re-exports the public API for users; a module of dsr_bench, generators or annotator
    imports from the module a name lives in (`from dsr_bench import __version__` aside), so that the graph above is
    the real one and importing the package stays light."""
    facade = [f"{path.relative_to(ROOT)}: {target}" for folder in ("dsr_bench", "generators", "annotator")
              for path in (ROOT / folder).rglob("*.py") for target in _imported(path)
              if target.startswith("dsr_bench.") and target.count(".") == 1
              and target.split(".")[1] in __import__("dsr_bench").__all__ and target != "dsr_bench.__version__"]
    assert facade == []


def test_the_cycle_finder_finds_a_cycle():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_one_installed_namespace():
    """The simulator and the annotator are installed as dsr_bench.generators and dsr_bench.annotator (pyproject's
    package-dir), never as top-level `generators` / `annotator`, which another distribution or a user's own folder
    would shadow (issue 45): no file imports those names, every package folder is in pyproject's list, and the entry
    points name the installed modules."""
    import tomllib

    sources = [p for folder in ("dsr_bench", "generators", "annotator", "tests", "scripts", "bench")
               for p in (ROOT / folder).rglob("*.py")]
    bare = [f"{path.relative_to(ROOT)}: {name}" for path in sources for name in _imported(path)
            if name.split(".")[0] in ("generators", "annotator")]
    bare += [f"{path.relative_to(ROOT)}: from {node.module}" for path in sources
             for node in ast.walk(ast.parse(path.read_text())) if isinstance(node, ast.ImportFrom) and node.module
             and node.level == 0 and node.module.split(".")[0] in ("generators", "annotator")]
    assert bare == []
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())
    setup = project["tool"]["setuptools"]
    assert setup["package-dir"] == {"dsr_bench.generators": "generators", "dsr_bench.annotator": "annotator"}
    folders = {".".join(p.parent.relative_to(ROOT).parts) for folder in ("dsr_bench", "generators", "annotator")
               for p in (ROOT / folder).rglob("__init__.py")}
    installed = {f"dsr_bench.{f}" if f.split(".")[0] in ("generators", "annotator") else f for f in folders}
    assert set(setup["packages"]) == installed
    points = [v for group in project["project"]["entry-points"].values() for v in group.values()]
    assert points and all(v.startswith("dsr_bench.") for v in points)
    import dsr_bench.annotator.session
    import dsr_bench.generators.episode

    assert Path(dsr_bench.generators.episode.__file__) == ROOT / "generators" / "episode.py"
    assert Path(dsr_bench.annotator.session.__file__) == ROOT / "annotator" / "session.py"


def test_a_users_own_generators_folder_does_not_shadow_the_simulator(tmp_path):
    """A working directory holding folders named `generators` and `annotator` (a user's own code): `python -m
    dsr_bench` still finds the simulator's and the annotator's commands (before issue 45: "No module named
    'generators.cli'")."""
    import os
    import subprocess
    import sys

    for name in ("generators", "annotator"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "__init__.py").write_text("raise ImportError('the user\\'s own package')\n")
    done = subprocess.run([sys.executable, "-m", "dsr_bench", "--help"], cwd=tmp_path, capture_output=True, text=True,
                          env={**os.environ, "COLUMNS": "200"}, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "generate-captures" in done.stdout and "annotate" in done.stdout

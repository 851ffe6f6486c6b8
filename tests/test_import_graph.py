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


def import_graph() -> dict[str, set[str]]:
    """{part: the other parts it imports}, over every module of dsr_bench."""
    edges: dict[str, set[str]] = defaultdict(set)
    for path in (ROOT / "dsr_bench").rglob("*.py"):
        me = _part(".".join(path.relative_to(ROOT).with_suffix("").parts))
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] == "dsr_bench":
                targets = [node.module] if node.module != "dsr_bench" else [f"dsr_bench.{a.name}" for a in node.names]
            elif isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            else:
                continue
            for target in targets:
                other = _part(target)
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


def test_the_cycle_finder_finds_a_cycle():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []

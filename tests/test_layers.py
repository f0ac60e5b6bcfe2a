"""The package's import layers (docs/design.md, "Layers"): no import loops, no upward imports.

Every ``import`` of a ``counterscene_env`` module counts: at module level, inside functions
(lazy imports) and under ``TYPE_CHECKING``. ``python tests/test_layers.py`` prints the graph.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "counterscene_env"

#: Layer of each module (by dotted prefix, most specific wins); a module may import only from
#: its own layer or lower ones. The order is the data flow of docs/design.md.
LAYERS = {
    "config": 0,
    "geometry": 0,
    "dynamics": 0,
    "ttc": 0,  # time to collision on geometry's separating axes
    "scene": 1,
    "metrics": 1,
    "adversary.tracks": 2,
    "adversary.conflicts": 2,
    "adversary.selection": 2,
    "world_model": 3,
    "adversary.schedules": 4,
    "adversary.guidance": 4,
    "adversary": 4,  # the package's lazy re-exports
    "sim": 5,
    "planners": 6,
    "envs": 7,
    "stress": 8,
    "bench": 8,  # times stress runs beside the env and highway-env
    "report": 9,  # reads stress runs, replays their episodes
    "cli": 10,
    "": 11,  # the package root: version and registration
}


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE).with_suffix("").parts
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def modules() -> dict[str, Path]:
    return {module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def resolve(name: str, known: dict[str, Path]) -> str | None:
    """``counterscene_env.a.b`` -> the known module ``a.b`` (or its nearest package)."""
    if name != "counterscene_env" and not name.startswith("counterscene_env."):
        return None
    rel = name.removeprefix("counterscene_env").lstrip(".")
    while rel not in known:
        rel = rel.rpartition(".")[0]
    return rel


def imports_of(path: Path, known: dict[str, Path]) -> set[str]:
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            # ``from pkg import sub`` imports the submodule when there is one (the package's
            # own ``__init__`` runs too, but as every package's does: not an edge here).
            subs = [f"{node.module}.{a.name}" for a in node.names]
            names = [n for n in subs if resolve(n, known) == n.removeprefix("counterscene_env.")]
            names = names or [node.module]
        else:
            continue
        out |= {m for n in names if (m := resolve(n, known)) is not None}
    return out


def graph() -> dict[str, set[str]]:
    known = modules()
    return {m: imports_of(p, known) - {m} for m, p in known.items()}


def layer(module: str) -> int:
    best = max((k for k in LAYERS if module == k or module.startswith(k + ".") or not k), key=len)
    return LAYERS[best]


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """Every import loop, as a path that returns to its start."""
    found, state = [], {}

    def visit(node: str, stack: list[str]) -> None:
        state[node] = "open"
        for nxt in sorted(edges.get(node, ())):
            if state.get(nxt) == "open":
                found.append([*stack[stack.index(nxt) :], nxt])
            elif nxt not in state:
                visit(nxt, [*stack, nxt])
        state[node] = "done"

    for node in sorted(edges):
        if node not in state:
            visit(node, [node])
    return found


def test_the_package_has_no_import_loops():
    assert cycles(graph()) == []


def test_no_module_imports_from_a_higher_layer():
    upward = [
        f"{m} (layer {layer(m)}) imports {d} (layer {layer(d)})"
        for m, deps in graph().items()
        for d in sorted(deps)
        if layer(d) > layer(m)
    ]
    assert upward == []


def test_the_checks_see_lazy_and_type_checking_imports(tmp_path):
    known = {"a": tmp_path / "a.py", "b": tmp_path / "b.py", "c": tmp_path / "c.py"}
    known["a"].write_text(
        "from typing import TYPE_CHECKING\n"
        "if TYPE_CHECKING:\n    from counterscene_env.b import X\n"
        "def f():\n    import counterscene_env.c\n"
    )
    assert imports_of(known["a"], known) == {"b", "c"}
    assert cycles({"a": {"b"}, "b": {"a"}}) == [["a", "b", "a"]]


if __name__ == "__main__":
    edges = graph()
    for module in sorted(edges, key=lambda m: (layer(m), m)):
        deps = ", ".join(sorted(edges[module])) or "-"
        print(f"[{layer(module)}] {module or 'counterscene_env'}: {deps}")
    loops = cycles(edges)
    print(f"{len(edges)} modules, {sum(map(len, edges.values()))} imports, {len(loops)} loops")
    sys.exit(bool(loops))

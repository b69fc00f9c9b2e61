"""The layers of docs/ARCHITECTURE.md, checked on the source: no upward import, no cycle, a pure core."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "src" / "escape_cli"

# Lower layers never import higher ones; a package may import itself (without cycles).
LAYERS = {
    "escape_cli.errors": 0,
    "escape_cli.version": 0,
    "escape_cli.formats": 0,
    "escape_cli.interrupts": 0,
    "escape_cli.piped_process": 0,
    "escape_cli.extras": 1,
    "escape_cli.packaged_models": 1,
    "escape_cli.core": 1,
    "escape_cli.io": 2,
    "escape_cli.data": 3,
    "escape_cli.inference": 3,
    "escape_cli.model_check": 2,
    "escape_cli.pipeline": 4,
    "escape_cli.engines": 5,
    "escape_cli.evaluation": 5,
    "escape_cli.eval_compare": 5,
    "escape_cli.render_png": 5,
    "escape_cli.nn": 5,
    "escape_cli.cli": 6,
    "escape_cli.__main__": 7,
}
FACADE = "escape_cli"  # the package's __init__: re-exports `complete` (lazily)
CORE_ALLOWED = {"numpy", "scipy", "__future__", "dataclasses", "math", "numbers", "itertools", "typing", "functools",
                "concurrent", "threading"}  # core/threads.py: one shared pool for independent batches (solver, neighbours)


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def modules() -> dict[str, Path]:
    return {module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def imports_of(path: Path, name: str) -> list[str]:
    """Every module imported anywhere in the file (top level and inside functions), absolute."""
    tree = ast.parse(path.read_text(), filename=str(path))
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.extend(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(anchor + ([base] if base else []))
            found.append(base)
            found.extend(f"{base}.{alias.name}" for alias in node.names)
    return found


def layer_of(module: str) -> tuple[str, int] | None:
    for prefix, rank in sorted(LAYERS.items(), key=lambda item: -len(item[0])):
        if module == prefix or module.startswith(prefix + "."):
            return prefix, rank
    return None


def internal_graph() -> dict[str, set[str]]:
    known = modules()
    graph: dict[str, set[str]] = {}
    for name, path in known.items():
        targets = set()
        for imported in imports_of(path, name):
            if imported in known and imported != name:
                targets.add(imported)
        graph[name] = targets
    return graph


def test_every_module_has_a_layer():
    missing = [name for name in modules() if name != FACADE and layer_of(name) is None]
    assert not missing, f"modules outside the layer table: {missing}"


def test_no_module_imports_a_higher_layer():
    upward = []
    for name, targets in internal_graph().items():
        if name == FACADE:
            continue
        src_layer, src_rank = layer_of(name)
        for target in targets:
            if target == FACADE:
                upward.append(f"{name} -> {target} (the facade)")
                continue
            dst_layer, dst_rank = layer_of(target)
            if dst_layer != src_layer and dst_rank >= src_rank:
                upward.append(f"{name} -> {target}")
    assert not upward, "imports that go up or sideways between layers:\n" + "\n".join(sorted(upward))


def test_no_import_cycles():
    graph = internal_graph()
    state: dict[str, int] = {}
    cycles = []

    def visit(node, stack):
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                cycles.append(stack[stack.index(nxt):] + [nxt])
            elif nxt not in state:
                visit(nxt, stack)
        stack.pop()
        state[node] = 2

    for node in sorted(graph):
        if node not in state:
            visit(node, [])
    assert not cycles, "import cycles: " + "; ".join(" -> ".join(c) for c in cycles)


@pytest.mark.parametrize("name", sorted(n for n in modules() if n.startswith("escape_cli.core")))
def test_core_is_pure(name):
    """The core imports numpy, scipy, the standard maths and escape_cli.errors only; no files, no printing."""
    path = modules()[name]
    outside = []
    for imported in imports_of(path, name):
        root = imported.split(".")[0]
        if root == "escape_cli":
            if not (imported.startswith("escape_cli.core") or imported.startswith("escape_cli.errors")) and imported != "escape_cli":
                outside.append(imported)
        elif root not in CORE_ALLOWED:
            outside.append(imported)
    assert not outside, f"{name} imports {sorted(set(outside))}"
    calls = {node.func.id for node in ast.walk(ast.parse(path.read_text()))
             if isinstance(node, ast.Call) and isinstance(node.func, ast.Name)}
    assert not calls & {"print", "open", "input"}, f"{name} calls {sorted(calls & {'print', 'open', 'input'})}"


def test_the_walker_sees_lazy_and_relative_imports(tmp_path):
    """The checks above are only as good as `imports_of`: it must find imports inside functions."""
    source = tmp_path / "mod.py"
    source.write_text("def f():\n    from escape_cli.cli import main\n    import escape_cli.nn.train\n")
    found = imports_of(source, "escape_cli.core.mod")
    assert "escape_cli.cli.main" in found and "escape_cli.nn.train" in found


def test_only_the_ray_engine_imports_ray():
    """Ray is an optional extra: one module imports it, and only when `--engine ray` asks."""
    importers = sorted(
        name for name, path in modules().items()
        if any(imported == "ray" or imported.startswith("ray.") for imported in imports_of(path, name))
    )
    assert importers == ["escape_cli.engines.ray_engine"]

"""The package's layers (docs/architecture.md): imports go one way, shared < guides < render < experiments, bench <
cli, with no cycle, imports inside functions included."""

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "guiding"

#: The layer of each subpackage; a module outside these is a shared one (layer 0), the package root the top.
LAYERS = {"guiding.guides": 1, "guiding.render": 2, "guiding.experiments": 3, "guiding.bench": 3, "guiding.cli": 4,
          "guiding.__main__": 4}


def modules(package: Path) -> dict[str, Path]:
    """Every module of ``package`` by its dotted name (a package by its own name)."""
    found = {}
    for path in package.rglob("*.py"):
        parts = list(path.relative_to(package.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        found[".".join(parts)] = path
    return found


def import_graph(package: Path) -> dict[str, set[str]]:
    """Module → the package's modules it imports anywhere in its code (at module level or inside functions)."""
    known = modules(package)
    root = package.name

    def owner(name: str) -> str:
        while name not in known and "." in name:
            name = name.rsplit(".", 1)[0]
        return name if name in known else ""

    graph = {name: set() for name in known}
    for name, path in known.items():
        here = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    parts = here.split(".")[: len(here.split(".")) - node.level + 1]
                    base = ".".join(parts + ([base] if base else []))
                submodules = [f"{base}.{alias.name}" for alias in node.names if f"{base}.{alias.name}" in known]
                targets = submodules or [base]
            else:
                continue
            graph[name] |= {owner(t) for t in targets if t.split(".")[0] == root and owner(t) not in ("", name)}
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on_stack, found = {}, {}, [], set(), []

    def visit(node):
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for other in graph[node]:
            if other not in index:
                visit(other)
                low[node] = min(low[node], low[other])
            elif other in on_stack:
                low[node] = min(low[node], index[other])
        if low[node] == index[node]:
            component = []
            while True:
                other = stack.pop()
                on_stack.discard(other)
                component.append(other)
                if other == node:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for node in graph:
        if node not in index:
            visit(node)
    return found


def layer(name: str) -> int:
    for prefix, rank in LAYERS.items():
        if name == prefix or name.startswith(prefix + "."):
            return rank
    return 0 if "." in name else 5


def wrong_way(graph: dict[str, set[str]]) -> list[tuple[str, str]]:
    """Imports of a higher layer, and between the two lab subpackages (experiments and bench)."""
    def subpackage(name):
        return name.split(".")[1]

    return sorted((a, b) for a, targets in graph.items() for b in targets
                  if layer(b) > layer(a) or (layer(a) == layer(b) == 3 and subpackage(a) != subpackage(b)))


def test_no_import_cycle():
    assert cycles(import_graph(PACKAGE)) == []


def test_imports_go_one_way():
    assert wrong_way(import_graph(PACKAGE)) == []


def test_the_checks_find_a_cycle_and_an_upward_import(tmp_path):
    """The two checks above can fail: a cycle through an import inside a function, and a guide importing render."""
    package = tmp_path / "guiding"
    (package / "guides").mkdir(parents=True)
    (package / "render").mkdir()
    for folder in (package, package / "guides", package / "render"):
        (folder / "__init__.py").write_text("")
    (package / "guides" / "a.py").write_text("def f():\n    from guiding.render import b\n")
    (package / "render" / "b.py").write_text("from guiding.guides.a import f\n")
    graph = import_graph(package)
    assert cycles(graph) == [["guiding.guides.a", "guiding.render.b"]]
    assert wrong_way(graph) == [("guiding.guides.a", "guiding.render.b")]

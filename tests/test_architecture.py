"""The package's shape: layers in pipeline order, imports one way down, no cycle, no private
name used outside its subpackage. The imports are read from the source (every ``import``, at
module level or inside a function), so a new upward import fails here before it can tangle."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from tests.import_graph import strongly_connected

PACKAGE = Path(__file__).resolve().parents[1] / "bayes_tfcrds"
#: lowest first; a module may import from its own layer and the layers before it
LAYERS = (
    "_version",
    "core",
    "output",
    "bundle",
    "physics",
    "simulate",
    "fit",
    "inference",
    "uncertainty",
    "discovery",
    "studies",
    "cli",
    "__main__",
    "__init__",
)


def _contract(layer: str) -> set:
    """The layers a subpackage may import, read from the "May import:" line of its docstring."""
    doc = (
        ast.get_docstring(ast.parse((PACKAGE / layer / "__init__.py").read_text(encoding="utf-8")))
        or ""
    )
    said = doc.split("May import:", 1)[1] if "May import:" in doc else ""
    said = said.split("(", 1)[0]  # a parenthesis explains, it grants nothing
    if "every layer below" in said:
        return set(LAYERS[: LAYERS.index(layer)])
    words = {w.strip(" ,.()").removeprefix("bayes_tfcrds.") for w in said.split()}
    return {w for w in words if w in LAYERS} | {"_version"}


def _module_name(path: Path) -> str:
    rel = path.relative_to(PACKAGE.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _layer(module: str) -> str:
    parts = module.split(".")
    return "__init__" if len(parts) == 1 else parts[1]


def _imports(path: Path):
    """(line, imported module, imported names) of every import of the package in ``path``."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            assert node.level == 0, (
                f"{path}:{node.lineno}: relative import (the package imports absolutely)"
            )
            if node.module and node.module.split(".")[0] == "bayes_tfcrds":
                yield node.lineno, node.module, [a.name for a in node.names]
        elif isinstance(node, ast.Import):
            for a in node.names:
                if a.name.split(".")[0] == "bayes_tfcrds":
                    yield node.lineno, a.name, []


def _graph() -> dict:
    graph = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        graph[_module_name(path)] = (path, list(_imports(path)))
    return graph


GRAPH = _graph()


def test_every_subpackage_is_a_layer_and_says_what_it_may_import():
    for init in PACKAGE.glob("*/__init__.py"):
        name = init.parent.name
        assert name in LAYERS, f"subpackage {name} has no place in LAYERS"
        doc = ast.get_docstring(ast.parse(init.read_text(encoding="utf-8"))) or ""
        assert "May import" in doc, (
            f"{init}: the docstring must state what the subpackage may import"
        )
    for path in PACKAGE.glob("*.py"):
        assert path.stem in LAYERS, f"top-level module {path.name} has no place in LAYERS"


@pytest.mark.parametrize("module", sorted(GRAPH))
def test_imports_go_one_way_down(module):
    path, imports = GRAPH[module]
    mine = LAYERS.index(_layer(module))
    for line, target, _ in imports:
        if target == "bayes_tfcrds":
            assert module == "bayes_tfcrds", (
                f"{path}:{line}: import the defining module, not the package"
            )
            continue
        theirs = LAYERS.index(_layer(target))
        assert theirs <= mine, (
            f"{path}:{line}: {module} ({LAYERS[mine]}) imports {target} ({LAYERS[theirs]}), a "
            "layer above it"
        )
        layer = _layer(module)
        if theirs < mine and (PACKAGE / layer / "__init__.py").exists():
            assert _layer(target) in _contract(layer), (
                f"{path}:{line}: {module} imports {target}, which {layer}/__init__.py does not "
                "allow"
            )


@pytest.mark.parametrize("module", sorted(GRAPH))
def test_no_private_name_crosses_a_subpackage(module):
    path, imports = GRAPH[module]
    for line, target, names in imports:
        if _layer(target) == _layer(module):
            continue
        private = [n for n in names if n.startswith("_") and n != "__version__"]
        assert not private, f"{path}:{line}: {module} takes private {private} from {target}"


def _cycles(graph: dict) -> list:
    """Import cycles of the package (groups of modules that import each other)."""
    edges = {
        m: sorted({t for _, t, _ in imps if t in graph and t != m})
        for m, (_, imps) in graph.items()
    }
    return strongly_connected(edges)


def test_no_import_cycle():
    assert _cycles(GRAPH) == []


def test_the_checks_can_fail():
    """The checks see a cycle and an upward import when there is one."""
    fake = {
        "bayes_tfcrds.core.a": (Path("a"), [(1, "bayes_tfcrds.fit.b", ["x"])]),
        "bayes_tfcrds.fit.b": (Path("b"), [(1, "bayes_tfcrds.core.a", ["_y"])]),
    }
    assert _cycles(fake) == [["bayes_tfcrds.core.a", "bayes_tfcrds.fit.b"]]
    assert LAYERS.index(_layer("bayes_tfcrds.fit.b")) > LAYERS.index(_layer("bayes_tfcrds.core.a"))
    assert "bundle" not in _contract("fit") and "physics" in _contract("fit")
    assert _contract("core") == {"_version"}

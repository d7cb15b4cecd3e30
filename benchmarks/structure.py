"""The package's shape in figures: modules per folder, import depth, cycles, private names taken
across modules, the longest functions and over-long lines.

Usage:  python benchmarks/structure.py [TREE]   (default: this checkout; TREE = another checkout,
        e.g. an old commit: git worktree add /tmp/old ae70138 && python benchmarks/structure.py
        /tmp/old)

Imports are read from the source (every import, also inside functions), nothing is run. Code lines
of a function exclude blank lines, comments and docstrings.
"""

from __future__ import annotations

import argparse
import ast
import collections
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the tests' helpers
from tests.import_graph import strongly_connected  # noqa: E402


def modules(root: Path) -> dict:
    """Dotted module name -> path, for every .py file of the package under ``root``."""
    out = {}
    for p in sorted(root.rglob("*.py")):
        parts = list(p.relative_to(root.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = p
    return out


def _target(mods, mod, node) -> str | None:
    if node.level == 0:
        return node.module
    base = mod.split(".")
    pkg = base if mods[mod].name == "__init__.py" else base[:-1]
    pkg = pkg[: len(pkg) - (node.level - 1)]
    return ".".join(pkg + ([node.module] if node.module else []))


def import_graph(mods: dict) -> tuple[dict, list]:
    """Module -> imported package modules, and (importer, module, name) of private names taken."""
    edges, private = collections.defaultdict(set), []
    for m, p in mods.items():
        for n in ast.walk(ast.parse(p.read_text(encoding="utf-8"))):
            if not isinstance(n, ast.ImportFrom):
                continue
            t = _target(mods, m, n)
            if not t or not t.startswith("bayes_tfcrds"):
                continue
            for a in n.names:
                if f"{t}.{a.name}" in mods:
                    edges[m].add(f"{t}.{a.name}")
                elif t in mods:
                    edges[m].add(t)
                    if a.name.startswith("_") and a.name != "__version__" and t != m:
                        private.append((m, t, a.name))
    return edges, private


def depth(edges: dict, mods: dict) -> int:
    """Longest chain of imports (in modules), back edges of a cycle ignored."""
    memo = {}

    def level(m, stack=()):
        if m in memo:
            return memo[m]
        if m in stack:
            return 0
        v = 1 + max((level(d, (*stack, m)) for d in edges.get(m, ()) if d != m), default=0)
        memo[m] = v
        return v

    return max(level(m) for m in mods)


def cycles(edges: dict, mods: dict) -> list:
    """Groups of modules that import each other (Tarjan, as the architecture test)."""
    return strongly_connected({m: sorted(edges.get(m, ())) for m in mods})


def code_lines(src_lines: list, node) -> int:
    """Lines of ``node`` that are neither blank, comments nor docstrings."""
    doc = set()
    for n in ast.walk(node):
        body = getattr(n, "body", None)
        if (
            isinstance(n, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef)
            and body
            and isinstance(body[0], ast.Expr)
            and isinstance(getattr(body[0], "value", None), ast.Constant)
            and isinstance(body[0].value.value, str)
        ):
            doc |= set(range(body[0].lineno, body[0].end_lineno + 1))
    count = 0
    for i in range(node.lineno, node.end_lineno + 1):
        text = src_lines[i - 1].strip()
        if text and not text.startswith("#") and i not in doc:
            count += 1
    return count


def longest_functions(mods: dict, n: int) -> list:
    rows = []
    for p in mods.values():
        src = p.read_text(encoding="utf-8")
        lines = src.splitlines()
        for node in ast.walk(ast.parse(src)):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                rows.append((code_lines(lines, node), f"{p}:{node.lineno} {node.name}"))
    return sorted(rows, reverse=True)[:n]


def long_lines(paths, limit=100) -> int:
    return sum(
        sum(len(line) > limit for line in p.read_text(encoding="utf-8").splitlines()) for p in paths
    )


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("tree", nargs="?", default=str(Path(__file__).resolve().parents[1]))
    ap.add_argument("--functions", type=int, default=5, help="how many of the longest to list")
    a = ap.parse_args(argv)
    tree = Path(a.tree)
    mods = modules(tree / "bayes_tfcrds")
    edges, private = import_graph(mods)
    folders = collections.Counter(
        str(p.parent.relative_to(tree)) for p in mods.values() if p.name != "__init__.py"
    )
    across = [x for x in private if x[0].split(".")[:2] != x[1].split(".")[:2]]
    print(f"modules (without __init__): {sum(folders.values())}")
    print("modules per folder: " + ", ".join(f"{k} {v}" for k, v in sorted(folders.items())))
    print(f"longest import chain (modules): {depth(edges, mods)}")
    print(f"import cycles: {len(cycles(edges, mods))} {cycles(edges, mods)}")
    print(
        f"private names imported from another module: {len(private)}; across subpackages "
        f"(or within a flat package): {len(across)}"
    )
    print("longest functions (code lines):")
    for count, where in longest_functions(mods, a.functions):
        print(f"  {count:4d}  {where}")
    pkg = list((tree / "bayes_tfcrds").rglob("*.py"))
    rest = [*(tree / "tests").rglob("*.py"), *(tree / "benchmarks").rglob("*.py")]
    print(
        f"lines over 100 characters: package {long_lines(pkg)}, with tests and benchmarks "
        f"{long_lines(pkg + rest)}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Cycles of an import graph (shared by tests/test_architecture.py and benchmarks/structure.py)."""

from __future__ import annotations


def strongly_connected(edges: dict) -> list:
    """Components of more than one node of the graph ``edges`` (node -> nodes it points to), each
    sorted; Tarjan's algorithm. An empty list means the graph has no cycle."""
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in edges.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(edges):
        if v not in index:
            visit(v)
    return out

"""models/ has no import circles, counting imports inside functions too (a lazy import still ties two modules)."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2] / "models"


def module_graph(root: Path) -> dict[str, set[str]]:
    """Module name → the models.* modules it imports anywhere in its source."""
    names = {}
    for path in root.rglob("*.py"):
        name = ".".join(path.with_suffix("").relative_to(root.parent).parts)
        names[name.removesuffix(".__init__")] = path
    graph = {}
    for name, path in names.items():
        deps = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module:
                targets = [node.module, *(f"{node.module}.{a.name}" for a in node.names)]
            elif isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            else:
                continue
            deps.update(t for t in targets if t in names and t != name)
        graph[name] = deps
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on_stack, out, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in graph:
        if v not in index:
            visit(v)
    return out


def test_cycle_finder_finds_a_known_circle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert cycles(graph) == [["a", "b", "c"]]


def test_models_has_no_import_circles():
    graph = module_graph(ROOT)
    assert "models.offline.evaluation.registry" in graph and "models.offline.jobs" in graph
    assert cycles(graph) == []

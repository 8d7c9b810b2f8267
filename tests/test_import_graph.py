"""The house rules a reader relies on: arrows run down and never round.

No import circles anywhere in the tree (lazy imports inside functions included: they hide a
circle, they do not remove it; so do the "module:function" names of a factory table such as
carrt/rig_table.py). The layers, bottom to top: firmware_bridge <- carrt <- training <- export, with
bench and research on top; a layer imports only from the layers below it, carrt never imports
torch (the car has none), and nothing in the simulator imports a command-line module (the CLI
is the top of carrt: the simulator is what it calls, not what it is built from). And no module so
long that it does more than one job.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
# Bottom to top. research/ and bench/ are globbed as they exist.
PACKAGES = tuple(
    p
    for p in ("firmware_bridge", "carrt", "training", "export", "bench", "research")
    if (ROOT / p).is_dir()
)
PRODUCT = ("carrt", "training", "export", "firmware_bridge")  # held to the line limit
MAX_LINES = 450
# who may not import whom (third-party names count too: carrt never imports torch)
FORBIDDEN = {
    "firmware_bridge": {"carrt", "training", "export", "bench", "research"},
    "carrt": {"training", "export", "bench", "research", "torch"},
    "training": {"export", "bench", "research"},
    "export": {"bench", "research"},
    "bench": {"research"},
}
FACTORY = re.compile(r"^([A-Za-z_][\w.]*):[A-Za-z_]\w*$")  # "package.module:attribute"


def project_modules(packages: tuple[str, ...] = PACKAGES) -> dict[str, Path]:
    modules = {}
    for package in packages:
        for path in (ROOT / package).rglob("*.py"):
            parts = list(path.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            modules[".".join(parts)] = path
    return modules


def imported_names(name: str, path: Path) -> set[str]:
    """Every dotted name the module imports, relative imports made absolute; `from pkg import
    x` yields pkg.x (x may be a submodule: resolving it finds the module that defines x); a
    "module:attribute" string constant (a factory named in a table, imported when chosen)
    yields the module."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                base = ".".join([*up, *([node.module] if node.module else [])])
            names |= {f"{base}.{alias.name}" for alias in node.names}
        elif isinstance(node, ast.Constant) and (match := FACTORY.match(str(node.value))):
            names.add(match.group(1))
    return names


def import_graph(modules: dict[str, Path]) -> dict[str, set[str]]:
    def resolve(name: str) -> str | None:
        parts = name.split(".")
        for end in range(len(parts), 0, -1):
            if ".".join(parts[:end]) in modules:
                return ".".join(parts[:end])
        return None

    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        targets = {resolve(n) for n in imported_names(name, path)}
        graph[name] = {t for t in targets if t and t != name}
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return found


def layer_breaches(layer: str, forbidden: set[str]) -> dict[str, list[str]]:
    """{module of `layer`: the forbidden names it imports}."""
    breaches = {}
    for name, path in project_modules((layer,)).items():
        bad = sorted(n for n in imported_names(name, path) if n.split(".")[0] in forbidden)
        if bad:
            breaches[str(path.relative_to(ROOT))] = bad
    return breaches


def is_cli_module(name: str) -> bool:
    """carrt's command-line layer: carrt.cli, carrt.__main__, carrt.*_cmd, any *.cli."""
    last = name.rpartition(".")[2]
    return last in ("cli", "__main__") or last.endswith("_cmd")


def test_no_import_circles_anywhere_in_the_tree():
    graph = import_graph(project_modules())
    assert len(graph) > 80
    assert "carrt.sim.rig" in graph["carrt.rig_table"], "tables of named factories count too"
    assert "carrt.rig_table" in graph["carrt.session"], "lazy imports count too"
    assert cycles(graph) == []


def test_the_cycle_finder_finds_a_cycle():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


@pytest.mark.parametrize("layer", sorted(set(FORBIDDEN) & set(PACKAGES)))
def test_arrows_run_down(layer):
    breaches = layer_breaches(layer, FORBIDDEN[layer])
    assert breaches == {}, f"{layer} may not import {sorted(FORBIDDEN[layer])}: {breaches}"


def test_the_layer_check_sees_a_breach():
    # a check that cannot fail proves nothing: carrt does import firmware_bridge
    assert layer_breaches("carrt", {"firmware_bridge"})


def test_the_simulator_imports_no_command_line_module():
    graph = import_graph(project_modules(("carrt", "firmware_bridge")))
    assert {"carrt.cli", "carrt.eval_cmd", "carrt.__main__", "carrt.episodes.cli"} <= {
        m for m in graph if is_cli_module(m)
    }
    breaches = {
        module: sorted(t for t in targets if is_cli_module(t))
        for module, targets in graph.items()
        if module.startswith("carrt.sim.") and any(is_cli_module(t) for t in targets)
    }
    assert breaches == {}, f"move the helpers these need out of the CLI: {breaches}"


def test_no_module_over_the_line_limit():
    long = {
        str(path.relative_to(ROOT)): n
        for path in project_modules(PRODUCT).values()
        if (n := len(path.read_text().splitlines())) > MAX_LINES
    }
    assert long == {}, f"split these (one job per module): {long}"

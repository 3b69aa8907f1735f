"""The import graph follows the data flow (docs/architecture.md): base, devices, offline, application.

Every `import` of the project is read from the source (at module level and inside functions alike),
so a cycle or an upward import hidden in a function body fails here too.
"""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
LAYERS = {"manus_core": 0, "rig": 1, "dataset_tools": 2, "manus_capture": 3}
MAX_LINES = 500


def _modules() -> dict[str, Path]:
    found = {}
    for package in LAYERS:
        for path in (REPO / package).rglob("*.py"):
            name = ".".join(path.relative_to(REPO).with_suffix("").parts)
            found[name.removesuffix(".__init__")] = path
    return found


def _imports(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """The project modules that `name` imports, anywhere in its source."""
    targets = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            candidates = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = name.split(".")[: len(name.split(".")) - node.level + (path.name == "__init__.py")]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            # `from package import module` imports that module; `from module import name` the module
            candidates = [f"{module}.{alias.name}" for alias in node.names]
        else:
            continue
        for candidate in candidates:
            while candidate and candidate not in modules:
                candidate = candidate.rpartition(".")[0]
            if candidate and candidate != name:
                targets.add(candidate)
    return targets


def _graph() -> dict[str, set[str]]:
    modules = _modules()
    return {name: _imports(name, path, modules) for name, path in modules.items()}


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one node (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []
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
                    work.append((child, iter(sorted(graph.get(child, ())))))
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


def _group(module: str) -> str:
    """The unit of a package-level cycle: a top-level module or a subpackage (rig.cameras)."""
    return ".".join(module.split(".")[:2])


def test_no_upward_import():
    upward = [f"{a} -> {b}" for a, targets in _graph().items() for b in targets
              if LAYERS[b.split(".")[0]] > LAYERS[a.split(".")[0]]]
    assert not upward, "imports against the data flow:\n" + "\n".join(sorted(upward))


def test_no_module_cycle():
    assert not _cycles(_graph())


def test_no_package_cycle():
    groups: dict[str, set[str]] = {}
    for a, targets in _graph().items():
        groups.setdefault(_group(a), set()).update(_group(b) for b in targets if _group(b) != _group(a))
    assert not _cycles(groups)


def test_the_base_imports_nothing_else():
    graph = _graph()
    assert not {b for a, targets in graph.items() if a.startswith("manus_core") for b in targets
                if not b.startswith("manus_core")}


def test_modules_stay_small():
    big = {name: n for name, path in _modules().items() if (n := len(path.read_text().splitlines())) > MAX_LINES}
    assert not big, f"modules over {MAX_LINES} lines: {big}"


def test_the_checker_finds_a_cycle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert not _cycles({"a": {"b"}, "b": set()})


def test_each_file_format_is_named_by_its_own_module():
    """frames.csv and ground_truth.h5 are opened through one module each (the names appear as code,
    not prose, nowhere else): no stage reads either by raw keys of its own."""
    owners = {"frames.csv": "manus_core.frames_csv", "ground_truth.h5": "manus_core.ground_truth"}
    found = []
    for name, path in _modules().items():
        tree = ast.parse(path.read_text())
        docstrings = {id(node.body[0].value) for node in ast.walk(tree)
                      if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef))
                      and node.body and isinstance(node.body[0], ast.Expr)}
        found += [(node.value, name) for node in ast.walk(tree) if isinstance(node, ast.Constant)
                  and node.value in owners and id(node) not in docstrings and owners[node.value] != name]
    assert not found, found


def test_only_the_cli_draws_bars_and_only_errors_defines_errors():
    """One progress protocol (library code never imports tqdm; manus_capture.bars draws) and one
    errors module (every exception class of the project lives in manus_core.errors)."""
    bars, errors = [], []
    for name, path in _modules().items():
        tree = ast.parse(path.read_text())
        imported = {alias.name.split(".")[0] for node in ast.walk(tree) if isinstance(node, ast.Import)
                    for alias in node.names}
        imported |= {(node.module or "").split(".")[0] for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)}
        if "tqdm" in imported and name != "manus_capture.bars":
            bars.append(name)
        if name != "manus_core.errors":
            errors += [f"{name}.{node.name}" for node in ast.walk(tree) if isinstance(node, ast.ClassDef)
                       and any(isinstance(b, ast.Name) and (b.id.endswith(("Error", "Exception")) or b.id == "ManusError")
                               for b in node.bases)]
    assert not bars, f"library code drawing bars: {bars}"
    assert not errors, f"error classes outside manus_core.errors: {errors}"

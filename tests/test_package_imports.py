"""The project's package layering, read from the source with `ast` (no import is executed): `app/` is
the CLI and wiring, nothing below it imports it, the packages import each other without cycles, and
project imports sit at module top unless a comment says why one is inside a function."""
from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("app", "race", "fileio", "solver_cpp", "vehicles", "tracks", "sim", "tracking", "planning", "sysid", "bench", "recording")


def _imports(path: Path) -> list[tuple[str, int]]:
    """(imported top-level project package, line) of every import in the file, wherever it is."""
    tree = ast.parse(path.read_text(), filename=str(path))
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names = [node.module]
        else:
            continue
        out.extend((n.split(".")[0], node.lineno) for n in names if n.split(".")[0] in PACKAGES)
    return out


def _unexplained_function_imports(path: Path) -> list[int]:
    """Lines of project imports inside a function (relative ones too) without a `#` comment on the
    import's line, on the line above it, or on the line above the run of imports it belongs to."""
    text = path.read_text()
    lines = text.splitlines()
    tree = ast.parse(text, filename=str(path))
    out = []
    for fn in ast.walk(tree):
        if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        for node in ast.walk(fn):
            if isinstance(node, ast.Import):
                project = any(alias.name.split(".")[0] in PACKAGES for alias in node.names)
            elif isinstance(node, ast.ImportFrom):
                project = node.level > 0 or (node.module or "").split(".")[0] in PACKAGES
            else:
                continue
            if not project:
                continue
            first = node.lineno - 1  # 0-based; walk up over the imports of the same run
            while first > 0 and lines[first - 1].strip().startswith(("from ", "import ")):
                first -= 1
            explained = lines[first - 1: node.end_lineno] if first > 0 else lines[: node.end_lineno]
            if not any("#" in line for line in explained):
                out.append(node.lineno)
    return sorted(set(out))


def _package_graph() -> dict[str, dict[str, list[str]]]:
    """package -> {imported package: ["file:line", ...]} (imports of itself left out)."""
    graph: dict[str, dict[str, list[str]]] = {p: {} for p in PACKAGES}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            for target, line in _imports(path):
                if target != package:
                    graph[package].setdefault(target, []).append(f"{path.relative_to(ROOT)}:{line}")
    return graph


def test_the_scanner_sees_imports_in_functions_and_from_forms(tmp_path):
    src = tmp_path / "m.py"
    src.write_text("import os\nimport sim.simulator as s\nfrom race import loop\n"
                   "def f():\n    from app.cli import UserError\n    from . import x\n")
    assert _imports(src) == [("sim", 2), ("race", 3), ("app", 5)]


def test_no_package_below_app_imports_app():
    graph = _package_graph()
    offenders = {p: where for p, deps in graph.items() if p != "app" for t, where in deps.items() if t == "app"}
    assert offenders == {}


def test_packages_import_each_other_without_cycles():
    graph = _package_graph()
    state: dict[str, int] = {}  # 1 = on the current path, 2 = done

    def visit(p: str, path: list[str]) -> None:
        state[p] = 1
        for q in graph[p]:
            if state.get(q) == 1:
                cycle = path[path.index(q):] + [p, q] if q in path else [p, q]
                edges = {f"{a} -> {b}": graph[a][b][:3] for a, b in zip(cycle[:-1], cycle[1:])}
                raise AssertionError(f"import cycle {' -> '.join(cycle)}: {edges}")
            if state.get(q) is None:
                visit(q, path + [p])
        state[p] = 2

    for p in PACKAGES:
        if p not in state:
            visit(p, [])


def test_the_function_import_check_wants_a_comment(tmp_path):
    src = tmp_path / "m.py"
    src.write_text("import sim\n"
                   "def f():\n    import os\n    from race import loop\n"  # line 4: no reason given
                   "def g():\n    # here: race imports this module\n    from race import loop\n    from sim import x\n"
                   "def h():\n    from . import plotting  # matplotlib on first use\n"
                   "def k():\n    from . import plotting\n")  # line 12: relative, no reason
    assert _unexplained_function_imports(src) == [4, 12]


def test_project_imports_are_at_module_top_unless_a_comment_says_why():
    offenders = [f"{path.relative_to(ROOT)}:{line}" for package in PACKAGES
                 for path in sorted((ROOT / package).rglob("*.py")) for line in _unexplained_function_imports(path)]
    assert offenders == []

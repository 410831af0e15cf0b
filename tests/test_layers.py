"""How the package is put together: layers point one way, no import cycles, a light command line."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import nlpsf

PACKAGE = Path(nlpsf.__file__).resolve().parent
#: Modules of the physics library: everything in nlpsf/ except the command line.
LIBRARY = sorted(p for p in PACKAGE.glob("*.py") if p.name not in ("__main__.py",))


def _ours(name: str) -> bool:
    """nlpsf's modules, and ``app``: the web layer's folder name in a source checkout."""
    return name.startswith("nlpsf") or name == "app" or name.startswith("app.")


def _imports(path: Path, package: str) -> set[str]:
    """Absolute names of the nlpsf (or app) modules a file imports (at any depth in the file)."""
    tree = ast.parse(path.read_text())
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names if _ours(a.name)}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                module = f"{base}.{node.module}" if node.module else base
                found.add(module)
                found |= {f"{module}.{a.name}" for a in node.names}
            elif node.module and _ours(node.module):
                found.add(node.module)
                found |= {f"{node.module}.{a.name}" for a in node.names}
    return found


def test_the_library_never_imports_the_cli_or_the_web_layer():
    for path in LIBRARY:
        imported = _imports(path, "nlpsf")
        bad = sorted(m for m in imported if m.startswith(("nlpsf.cli", "nlpsf.web")) or m == "app" or m.startswith("app."))
        assert not bad, f"{path.name} imports {bad}"


def test_library_modules_import_without_cycles():
    graph = {}
    for path in LIBRARY:
        name = f"nlpsf.{path.stem}" if path.stem != "__init__" else "nlpsf"
        modules = {p.stem for p in LIBRARY}
        graph[name] = {m for m in _imports(path, "nlpsf") if m.count(".") == 1 and m.split(".")[1] in modules and m != name}
    # Depth-first search for a back edge.
    state: dict[str, int] = {}

    def visit(node: str, trail: list[str]) -> None:
        state[node] = 1
        for nxt in graph.get(node, ()):
            if state.get(nxt) == 1:
                raise AssertionError(f"import cycle: {' -> '.join([*trail, node, nxt])}")
            if nxt not in state:
                visit(nxt, [*trail, node])
        state[node] = 2

    for node in graph:
        if node not in state:
            visit(node, [])


def _modules_after(code: str) -> set[str]:
    out = subprocess.run(
        [sys.executable, "-c", f"import sys; {code}; print(' '.join(sorted(sys.modules)))"],
        capture_output=True,
        text=True,
        check=True,
    )
    return set(out.stdout.split())


def test_help_and_solve_import_nothing_heavy():
    # `nlpsf --help`, and a table solve, must not pay for scipy, astropy or the simulator.
    heavy = {"scipy", "astropy", "nlpsf.experiment", "nlpsf.moments", "nlpsf.optics", "fastapi", "uvicorn"}
    helped = _modules_after("from nlpsf.cli import build_parser; build_parser(['--help'])")
    assert not heavy & helped
    solved = _modules_after("from nlpsf import solve; solve('H158', magnitude=18.3, tolerance=1e-4)")
    assert not heavy & solved, heavy & solved
    # The worst over the focal plane reads the field-point tables' companion just as lightly.
    worst = _modules_after("from nlpsf.solver import solve_over_field; solve_over_field('H158', magnitude=18.3, tolerance=1e-4)")
    assert not heavy & worst, heavy & worst


def test_public_api_is_importable_from_the_package():
    from nlpsf import SimulationConfig, load_tables, simulate, slopes, solve

    assert callable(solve) and callable(simulate) and callable(slopes) and callable(load_tables)
    assert SimulationConfig().band == "H158"
    assert (PACKAGE / "py.typed").exists()

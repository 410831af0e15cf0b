"""How the package is put together: layers point one way, no import cycles, a light command line."""

from __future__ import annotations

import ast
import io
import re
import subprocess
import sys
import tokenize
import tomllib
from pathlib import Path

import nlpsf

PACKAGE = Path(nlpsf.__file__).resolve().parent
ROOT = PACKAGE.parent
#: Modules of the physics library: everything in nlpsf/ and its code subpackages (nlpsf.slopes.tables, ...)
#: except the command line.
LIBRARY = sorted(
    p for p in PACKAGE.rglob("*.py") if p.name != "__main__.py" and p.relative_to(PACKAGE).parts[0] not in ("cli", "data")
)


def _module_name(path: Path) -> str:
    """``nlpsf/slopes/tables/model.py`` -> ``nlpsf.slopes.tables.model``; a package's ``__init__.py`` -> the package."""
    parts = ("nlpsf", *path.relative_to(PACKAGE).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _package_of(path: Path) -> str:
    """The package relative imports in this file start from."""
    name = _module_name(path)
    return name if path.name == "__init__.py" else name.rpartition(".")[0]


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


def test_relative_imports_resolve_from_each_files_own_package():
    # The layering and cycle tests below read imports by name; a wrong base would hide edges.
    assert _module_name(PACKAGE / "slopes" / "tables" / "model.py") == "nlpsf.slopes.tables.model"
    assert _package_of(PACKAGE / "slopes" / "tables" / "model.py") == "nlpsf.slopes.tables"
    assert _package_of(PACKAGE / "slopes" / "tables" / "__init__.py") == "nlpsf.slopes.tables"
    imported = _imports(PACKAGE / "slopes" / "tables" / "model.py", "nlpsf.slopes.tables")
    assert {"nlpsf.defaults", "nlpsf.slopes.tables.splines"} <= imported


def test_every_import_of_ours_resolves():
    # Imports inside functions run only when called: a module moved to another package must not
    # leave one behind that names its old neighbours (``from . import x`` with no x there).
    import importlib
    import importlib.util

    for path in sorted(PACKAGE.rglob("*.py")):
        if path.relative_to(PACKAGE).parts[0] == "data":
            continue
        package = _package_of(path)
        for node in ast.walk(ast.parse(path.read_text())):
            if not isinstance(node, ast.ImportFrom) or not (node.level or (node.module or "").startswith("nlpsf")):
                continue
            base = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
            module = (f"{base}.{node.module}" if node.module else base) if node.level else node.module
            assert importlib.util.find_spec(module) is not None, f"{path}: {module}"
            imported = importlib.import_module(module)
            for alias in node.names:
                found = hasattr(imported, alias.name) or (
                    hasattr(imported, "__path__") and importlib.util.find_spec(f"{module}.{alias.name}") is not None
                )
                assert found, f"{path}: {module}.{alias.name}"


def test_the_library_never_imports_the_cli_or_the_web_layer():
    for path in LIBRARY:
        imported = _imports(path, _package_of(path))
        bad = sorted(m for m in imported if m.startswith(("nlpsf.cli", "nlpsf.web")) or m == "app" or m.startswith("app."))
        assert not bad, f"{path.name} imports {bad}"


#: The library's layers, lowest first: a module imports its own layer or a lower one, never a higher
#: one (docs/contributing.md's flow: the Roman data, the simulator, the request, the slopes, the
#: calculator, the calibration capability). Top-level modules (defaults, checks, flags, ...) sit below
#: them all; the package's ``__init__`` (the public API, lazily) above.
LAYERS = ("roman", "sim", "request", "slopes", "solve", "calibration")


def _layer(module: str) -> int:
    """A module's rank in :data:`LAYERS`; -1 for the top-level modules, len(LAYERS) for ``nlpsf`` itself."""
    parts = module.split(".")
    if module == "nlpsf":
        return len(LAYERS)
    if len(parts) > 1 and parts[1] in LAYERS:
        return LAYERS.index(parts[1])
    return -1


def test_the_library_layers_import_downwards_only():
    modules = {_module_name(p) for p in LIBRARY}
    upward = []
    for path in LIBRARY:
        name = _module_name(path)
        if name == "nlpsf":
            continue
        for imported in _imports(path, _package_of(path)):
            # ``from nlpsf import defaults`` names the package too: its modules are the edges.
            if imported != "nlpsf" and imported in modules and _layer(imported) > _layer(name):
                upward.append(f"{name} -> {imported}")
    assert not upward, sorted(upward)


def test_library_modules_import_without_cycles():
    modules = {_module_name(p) for p in LIBRARY}
    graph = {}
    for path in LIBRARY:
        name = _module_name(path)
        # A module's own packages are being imported already when it runs (``from . import x`` in
        # nlpsf/slopes/tables/model.py is no edge to nlpsf.slopes.tables), and the top package re-exports lazily.
        ancestors = {name.rsplit(".", k)[0] for k in range(1, name.count(".") + 1)} | {"nlpsf"}
        graph[name] = {m for m in _imports(path, _package_of(path)) if m in modules and m != name and m not in ancestors}
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
    heavy = {
        "scipy",
        "astropy",
        "nlpsf.sim.experiment",
        "nlpsf.sim.moments",
        "nlpsf.sim.optics",
        "fastapi",
        "uvicorn",
        "threadpoolctl",
    }
    helped = _modules_after("from nlpsf.cli import build_parser; build_parser(['--help'])")
    assert not heavy & helped
    solved = _modules_after("from nlpsf import solve; solve('H158', magnitude=18.3, tolerance=1e-4, scene='paper')")
    assert not heavy & solved, heavy & solved
    # The worst over the focal plane reads the field-point tables' companion just as lightly.
    over_field = "solve_over_field('H158', magnitude=18.3, tolerance=1e-4, scene='paper')"
    worst = _modules_after(f"from nlpsf.solve.solver import solve_over_field; {over_field}")
    assert not heavy & worst, heavy & worst


def test_public_api_is_importable_from_the_package():
    from nlpsf import SimulationConfig, load_tables, simulate, slopes, solve

    assert callable(solve) and callable(simulate) and callable(slopes) and callable(load_tables)
    assert SimulationConfig().band == "H158"
    assert (PACKAGE / "py.typed").exists()


def test_every_code_package_ships_in_the_wheel():
    # setuptools installs only the packages pyproject lists: a new subpackage left out of the list
    # works in the checkout and is missing from every installed copy.
    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    packages = {_module_name(p) for p in PACKAGE.rglob("__init__.py") if "data" not in p.relative_to(PACKAGE).parts}
    assert packages <= listed, packages - listed


def test_the_table_path_reads_curves_and_rows_without_scipy_or_astropy():
    # What the service's calculator and its curve and download endpoints read at start and per request.
    heavy = {"scipy", "astropy", "nlpsf.sim.experiment", "nlpsf.sim.optics", "nlpsf.slopes.tablebuild"}
    code = (
        "from nlpsf.slopes import tables; t = tables.load_tables(); t.get('K213', 3).slope('e', 'scatter', [20.0], 100.0, 1e-6);"
        " tables.curve('H158', 18, 'e1', 'bias', tables=t); tables.table_rows('J129', 7, tables=t);"
        " tables.load_tables(str(tables.field_table_path())).at_point(2).get('H158', 18).values('size', 'bias', [19.0])"
    )
    loaded = _modules_after(code)
    assert not heavy & loaded, heavy & loaded


#: Private functions one module still calls in another. Each is a concept with two owners; make the
#: function public where it lives (issue 16) and delete its line here. New entries fail the test.
KNOWN_PRIVATE_CALLS: set[tuple[str, str]] = set()


def _private_calls(path: Path) -> set[str]:
    """``module._name`` attribute reads on names bound by importing an nlpsf module."""
    tree = ast.parse(path.read_text())
    bound = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and (node.level or (node.module or "").startswith("nlpsf")):
            bound |= {a.asname or a.name for a in node.names}
    return {
        f"{node.value.id}.{node.attr}"
        for node in ast.walk(tree)
        if isinstance(node, ast.Attribute)
        and isinstance(node.value, ast.Name)
        and node.value.id in bound
        and node.attr.startswith("_")
        and not node.attr.startswith("__")
    }


def test_modules_call_each_others_public_names_only():
    web = sorted((ROOT / "app").glob("*.py")) if (ROOT / "app").is_dir() else []
    found = {(_module_name(p), call) for p in LIBRARY for call in _private_calls(p)}
    found |= {(f"nlpsf.web.{p.stem}", call) for p in web for call in _private_calls(p)}
    assert found <= KNOWN_PRIVATE_CALLS, sorted(found - KNOWN_PRIVATE_CALLS)


#: The simulation package in the order its modules may import each other (each only from earlier ones).
EXPERIMENT_LAYERS = ("config", "prepared", "results", "readout", "validity", "correction", "kernels", "measure")


def test_the_experiment_package_imports_one_way():
    for index, name in enumerate(EXPERIMENT_LAYERS):
        path = PACKAGE / "sim" / "experiment" / f"{name}.py"
        inside = {
            m.split(".")[3]
            for m in _imports(path, "nlpsf.sim.experiment")
            if m.startswith("nlpsf.sim.experiment.") and m.count(".") >= 2
        }
        later = inside & set(EXPERIMENT_LAYERS[index:])
        assert not later, (name, later)
    # Every name the old single module had is still there for its callers.
    from nlpsf.sim import experiment

    for name in ("SimulationConfig", "Scene", "prepare", "simulate", "slopes", "SlopeResult", "SimulationResult", "Statistic"):
        assert hasattr(experiment, name), name
    for name in ("nl_images", "_perturbed_fit", "_cut_jump_flags", "check_magnitudes", "check_sigma_beta", "METRICS"):
        assert hasattr(experiment, name), name


#: No module over 600 lines, no function over 80 (issue 25): the library, its command line, the web
#: layer, and the scripts, benchmarks and tests beside them.
MAX_MODULE_LINES = 600
MAX_FUNCTION_LINES = 80


def _code_files() -> list[tuple[str, Path]]:
    """(module name, path) of every code file of the library, its command line and the web layer."""
    files = [(_module_name(p), p) for p in PACKAGE.rglob("*.py") if "data" not in p.relative_to(PACKAGE).parts]
    web = sorted((ROOT / "app").glob("*.py")) if (ROOT / "app").is_dir() else []
    return files + [(f"nlpsf.web.{p.stem}", p) for p in web]


def _sized_files() -> list[tuple[str, Path]]:
    """:func:`_code_files`, and where a checkout has them the scripts, benchmarks and tests (by their paths)."""
    folders = [ROOT / name for name in ("scripts", "benchmarks", "tests") if (ROOT / name).is_dir()]
    beside = [path for folder in folders for path in sorted(folder.rglob("*.py"))]
    return _code_files() + [(str(path.relative_to(ROOT)), path) for path in beside]


def test_modules_and_functions_are_small():
    long_modules, long_functions = set(), set()
    for name, path in _sized_files():
        text = path.read_text()
        if len(text.splitlines()) > MAX_MODULE_LINES:
            long_modules.add(name)
        for node in ast.walk(ast.parse(text)):
            if (
                isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))
                and node.end_lineno - node.lineno + 1 > MAX_FUNCTION_LINES
            ):
                long_functions.add((name, node.name))
    assert not long_functions, sorted(long_functions)
    assert not long_modules, sorted(long_modules)


#: A preset's name as a literal, in either quote.
_PRESET_WORD = r"""["'](?:roman|paper|galsim-roman)["']"""
#: What names a preset, a default scene, the shipped measurement a preset reads or the rule its model part combines by.
_PRESET_THING = r"(?:preset|default|combine|scene|measured)"
#: A request's preset decided by its name: compared, or the Roman default's NAME or ``is_paper`` read;
#: or a preset's name compared as a literal with something that names a preset, a default scene, a
#: measurement or a combination rule (``default == "roman"``, ``info["combine"] != "roman"``,
#: ``settings.get("scene", "paper") == "roman"``, ``"paper" == preset``, ``scene in ("roman", ...)``).
PRESET_BY_NAME = re.compile(
    r"\bpreset\s*[!=]=|[!=]=\s*preset\b|\b(?:roman_default|presets)\.NAME\b|\bis_paper\b|\.preset\s+(?:not\s+)?in\b"
    rf"|{_PRESET_THING}[^=!\n]{{0,60}}?[!=]=\s*{_PRESET_WORD}"
    rf"|{_PRESET_WORD}\s*[!=]=[^\n]{{0,40}}?{_PRESET_THING}"
    rf"|{_PRESET_THING}[^=!\n]{{0,60}}?\bin\s*[(\[{{]\s*{_PRESET_WORD}"
)
#: The one comparison with such a word that is no preset: beta's sign convention ("paper": S = Q - beta Q^2).
SIGN_CONVENTION = re.compile(r"""\b\w*convention\s*==\s*["']paper["']""")
#: The files that may: the presets themselves, and the request read once (which names them).
DECIDE_BY_PRESET_NAME = {"nlpsf/request/presets.py", "nlpsf/request/resolve.py"}


def _code_of(text: str) -> str:
    """``text`` without its comments, and with every string that is not a bare word (docstrings,
    messages) emptied: what the code compares, not what its words say."""
    out = []
    for token in tokenize.generate_tokens(io.StringIO(text).readline):
        if token.type == tokenize.COMMENT:
            continue
        value = token.string
        if token.type == tokenize.STRING and not re.fullmatch(r"""["'][\w-]*["']""", value):
            value = '""'
        out.append(token._replace(string=value))  # kept at its place: an emptied string ends where it did
    return tokenize.untokenize(out)


def _decides_by_preset_name(text: str) -> bool:
    return bool(PRESET_BY_NAME.search(SIGN_CONVENTION.sub("", _code_of(text))))


def test_the_preset_name_pattern_finds_comparisons_and_passes_the_sign_convention():
    for code in (
        'if default == "roman":\n    pass\n',
        'x = a if info["combine"] != "roman" else b\n',
        'ok = t.meta["settings"].get("scene", "paper") != "roman"\n',
        "ok = 'paper' == request.preset\n",
        'ok = scene_name in ("roman", "paper")\n',
        "ok = roman_default.NAME\n",
        "ok = request.is_paper\n",
    ):
        assert _decides_by_preset_name(code), code
    for code in (
        'betas = [defaults.BETA0 if args.beta_convention == "paper" else -defaults.BETA0]\n',
        '"""When ``default == "roman"`` the docstring says so."""\n',
        'x = 1  # default == "roman" in a comment\n',
        'hint = "the default scene" if name == "roman" else ""\n',
        'if lowered == "roman":\n    kernel = ROMAN_IPC_KERNEL\n',
    ):
        assert not _decides_by_preset_name(code), code


def test_only_the_request_decides_by_the_presets_name():
    # Everything else asks the request's policy (``presets.Policy``: field grid, SCA range, the
    # measurements its answers read, ...) or the typed values a preset's data carry (a model part's
    # ``model_part.Rule``), so a preset is data, not a name compared in many files.
    found = set()
    for _, path in _code_files():
        if _decides_by_preset_name(path.read_text()):
            found.add(path.relative_to(ROOT).as_posix() if path.is_relative_to(ROOT) else str(path))
    assert found <= DECIDE_BY_PRESET_NAME, sorted(found - DECIDE_BY_PRESET_NAME)

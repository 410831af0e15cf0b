"""docs/contributing.md follows the code: every file its layout table and its "add a scene effect"
recipe name exists, every package of nlpsf is in the layout table, and every name a recipe step
cites (``module's name``, ``Class.method``) is defined in the file that step names."""

from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
GUIDE = (ROOT / "docs" / "contributing.md").read_text()
PATH = re.compile(r"`((?:nlpsf|app|static|tests|scripts|docs)/[\w/.-]+)`")


def section(title: str) -> str:
    start = GUIDE.index(f"## {title}")
    end = GUIDE.find("\n## ", start + 1)
    return GUIDE[start : end if end > 0 else None]


def defined_names(path: Path) -> set[str]:
    """Top-level names, and Class.method, a Python file defines."""
    tree = ast.parse(path.read_text())
    names = set()
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.ClassDef)):
            names.add(node.name)
        if isinstance(node, ast.ClassDef):
            names |= {f"{node.name}.{item.name}" for item in node.body if isinstance(item, ast.FunctionDef)}
            names |= {f"{node.name}.{item.target.id}" for item in node.body if isinstance(item, ast.AnnAssign)}
        elif isinstance(node, (ast.Assign, ast.AnnAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            names |= {t.id for t in targets if isinstance(t, ast.Name)}
    return names


def test_every_file_the_guide_names_exists():
    for text in (section("Layout"), section("Adding a scene effect: a worked example")):
        for path in PATH.findall(text):
            assert (ROOT / path.rstrip("/")).exists(), path


def test_the_layout_table_names_every_package():
    table = section("Layout")
    for init in sorted((ROOT / "nlpsf").rglob("__init__.py")):
        package = init.parent.relative_to(ROOT)
        if "data" in package.parts:
            continue
        top = "/".join(package.parts[:2])
        assert f"`{top}/`" in table or f"`{package.as_posix()}/`" in table or package.name in table, package


#: Names the recipe adds (they do not exist until a reader follows it).
NEW = {"MAX_RECIPROCITY", "Q_REF"}


def test_every_name_the_recipe_cites_is_defined_in_the_files_it_names():
    recipe = section("Adding a scene effect: a worked example")
    assert len(re.findall(r"\n\d+\. \*\*", recipe)) == 9
    files = [ROOT / p for p in PATH.findall(recipe) if p.endswith(".py") and "tests" not in p]
    names = set().union(*(defined_names(f) for f in files if f.is_file()))
    cited = set(re.findall(r"`([A-Za-z_]\w*(?:\.[A-Za-z_]\w*)?)`", recipe))
    code_names = {c for c in cited if (c[0].isupper() and c.isidentifier() and not c.isupper()) or "." in c or "_" in c}
    code_names = {c for c in code_names if not c.startswith(("nlpsf", "app")) and c not in NEW and not c.endswith(".py")}
    code_names -= {"reciprocity_alpha", "nl_polynomial", "scene_effects", "scene_model_uncertainty.json"}
    missing = sorted(c for c in code_names if c not in names and c.split(".")[-1] not in names)
    assert not missing, missing
    assert len(code_names) >= 12, sorted(code_names)

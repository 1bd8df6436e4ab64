"""The install itself: every package the code imports is declared, and the cv2 that wins is the
headless build the project declares."""

import ast
import re
import sys
import tomllib
from importlib.metadata import packages_distributions
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
OWN = {"worldenv_core", "stages", "tests"}


def _imports(paths) -> set[str]:
    names = set()
    for path in paths:
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names |= {a.name.split(".")[0] for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names.add(node.module.split(".")[0])
    return names - OWN - set(sys.stdlib_module_names)


def _norm(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def _declared() -> set[str]:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    specs = project["dependencies"] + [d for extra in project["optional-dependencies"].values() for d in extra]
    return {_norm(re.split(r"[\s\[<>=!~;]", s, maxsplit=1)[0]) for s in specs}


def test_every_directly_imported_package_is_declared():
    code = [p for d in ("worldenv_core", "stages") for p in (ROOT / d).rglob("*.py")]
    dists = packages_distributions()
    declared = _declared()
    undeclared = {}
    for name in sorted(_imports(code)):
        providers = {_norm(d) for d in dists.get(name, [])}
        assert providers, f"`import {name}` is provided by no installed distribution"
        if not providers & declared:
            undeclared[name] = sorted(providers)
    assert not undeclared, f"imported but not declared in pyproject.toml: {undeclared}"


def test_cv2_is_the_declared_headless_build():
    import cv2

    gui = [line.split(":", 1)[1].strip() for line in cv2.getBuildInformation().splitlines()
           if line.strip().startswith("GUI:")]
    assert gui == ["NONE"], f"cv2 {cv2.__version__} is a GUI build ({gui}); `make setup` reinstalls the headless one"
    pinned = re.search(r"opencv-python-headless==([0-9.]+)", (ROOT / "pyproject.toml").read_text()).group(1)
    assert pinned.startswith(cv2.__version__)
    assert cv2.imencode(".png", __import__("numpy").zeros((4, 4, 3), "uint8"))[0]

"""Packaging: installed, the project is one top-level package, ``diffkin`` (with ``diffkin.envs`` and
``diffkin.training`` mapped from the repository's ``envs/`` and ``training/``), and nothing imports the
repository folders under their bare names."""

from __future__ import annotations

import ast
import json
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

tomllib = pytest.importorskip("tomllib")  # Python 3.11+

ROOT = Path(__file__).resolve().parents[1]
MAPPED = {"diffkin.envs": "envs", "diffkin.training": "training"}


def _pyproject() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())


def _package_dirs() -> set[str]:
    """Every folder with an ``__init__.py`` under diffkin/, envs/ and training/, as installed names (plus
    diffkin.models.data, the bundled robots)."""
    out = {"diffkin.models.data"}
    for top, name in (("diffkin", "diffkin"), ("envs", "diffkin.envs"), ("training", "diffkin.training")):
        for init in (ROOT / top).rglob("__init__.py"):
            rel = init.parent.relative_to(ROOT / top).parts
            out.add(".".join((name, *rel)))
    return out


def test_the_package_list_covers_the_tree():
    tool = _pyproject()["tool"]["setuptools"]
    assert set(tool["packages"]) == _package_dirs()
    assert tool["package-dir"] == MAPPED


def test_nothing_imports_envs_or_training_by_their_bare_names():
    offenders = []
    for folder in ("diffkin", "envs", "training", "tests", "benchmarks", "scripts"):
        for path in (ROOT / folder).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                names = []
                if isinstance(node, ast.Import):
                    names = [a.name for a in node.names]
                elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                    names = [node.module]
                offenders += [f"{path.relative_to(ROOT)}:{node.lineno} {n}" for n in names
                              if n.split(".")[0] in ("envs", "training")]
    assert offenders == []


@pytest.mark.slow
def test_the_wheel_holds_only_diffkin(tmp_path):
    """``pip install .`` puts only ``diffkin`` (and its metadata) into site-packages."""
    out = subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation",
                          str(ROOT), "-w", str(tmp_path)], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-2000:]
    (wheel,) = tmp_path.glob("diffkin-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    assert {n.split("/")[0] for n in names} == {"diffkin", wheel.name.split("-py")[0] + ".dist-info"}
    for must in ("diffkin/py.typed", "diffkin/envs/reach.py", "diffkin/training/train.py",
                 "diffkin/models/data/panda.yaml", "diffkin/models/data/ur5.urdf"):
        assert must in names
    # every data file the package reads at run time ships: the C sources (all #included by _native.c), the
    # robots loadable by name and every file of their catalogue
    tree = ROOT / "diffkin"
    data = [p for p in tree.rglob("*") if p.is_file() and p.suffix not in (".py", ".pyc")
            and "__pycache__" not in p.parts]
    robots = tree / "models" / "robots"
    held = [robots / r["file"] for r in json.loads((robots / "catalog.json").read_text())["robots"]
            if not r["wheel"]]  # their licence keeps them out: the file, and its folder's other files
    held_dirs = {h.parent for h in held if h.parent.parent.name == "mjcf"}
    out = {p for p in data if p in held or p.parent in held_dirs}
    assert held and out and not {str(p.relative_to(ROOT)) for p in out} & set(names)
    missing = sorted(str(p.relative_to(ROOT)) for p in data if p not in out
                     and str(p.relative_to(ROOT)) not in names)
    assert not missing, f"not in the wheel: {missing}"
    # every robot the wheel carries has its licence text beside it
    for r in json.loads((robots / "catalog.json").read_text())["robots"]:
        path = (robots / r["file"]).resolve()
        if r["wheel"] and robots in path.parents:
            beside = [n for n in names if n.startswith(str(path.parent.relative_to(ROOT)) + "/")
                      and "LICENSE" in n.rsplit("/", 1)[1] and (path.parent.name != "urdf" or path.stem in n)]
            assert beside, f"{r['name']}: no licence text beside it in the wheel"

"""Every dependency pyproject.toml declares (runtime and the `dev` extra) imports in this environment, as the
README's install leaves it; and no project module imports torchvision (the package index's build need not
import beside the pinned CPU torch)."""

from __future__ import annotations

import importlib
import importlib.metadata
import re
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
DECLARED = [*PROJECT["dependencies"], *PROJECT["optional-dependencies"]["dev"]]


def _dist_name(requirement: str) -> str:
    """The distribution name of a PEP 508 requirement ("dask[distributed]>=2024.8" -> "dask")."""
    return re.match(r"[A-Za-z0-9._-]+", requirement).group(0)


def _modules(dist: str) -> list[str]:
    """Top-level import names the installed distribution provides: its packages, modules and extension
    modules (from the files its metadata lists; private `_x` names left out)."""
    names = set()
    for f in importlib.metadata.distribution(dist).files or []:
        top = f.parts[0]
        if len(f.parts) > 1 and f.name == "__init__.py":
            names.add(top)
        elif len(f.parts) == 1 and f.suffix in (".py", ".so", ".pyd"):
            names.add(top.split(".")[0])
    return sorted(n for n in names if not n.startswith("_") and n.isidentifier())


@pytest.mark.parametrize("requirement", DECLARED, ids=_dist_name)
def test_declared_dependency_imports(requirement):
    dist = _dist_name(requirement)
    importlib.metadata.version(dist)  # installed (PackageNotFoundError otherwise)
    modules = _modules(dist)
    assert modules, f"{dist}: installed but provides no importable top-level module"
    for name in modules:
        importlib.import_module(name)
    if "[distributed]" in requirement:
        importlib.import_module("distributed")


def test_no_project_module_imports_torchvision():
    folders = [p for p in ROOT.iterdir() if p.is_dir() and (p / "__init__.py").exists()]
    offenders = [
        str(f.relative_to(ROOT))
        for folder in folders
        for f in folder.rglob("*.py")
        if re.search(r"^\s*(import|from)\s+torchvision\b", f.read_text(), re.M)
    ]
    assert not offenders and folders

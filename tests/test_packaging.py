"""Packaging tells the truth: every package the code imports is declared in pyproject.toml (the
library's in `dependencies`, the tests' in the `test` extra, Mitsuba in `compare`), and the declared floors are met
by what is installed; the jax floor has `jax.shard_map(..., check_vma=...)`, which `render` calls."""

from __future__ import annotations

import ast
import importlib.metadata
import inspect
import re
import sys
import tomllib

import jax

from helpers import REPO

PYPROJECT = tomllib.loads((REPO / "pyproject.toml").read_text())
IMPORT_TO_DIST = {"OpenImageIO": "openimageio", "drjit": "mitsuba"}
"""Import names whose distribution has another name (drjit comes with mitsuba)."""
LOCAL = {"jaxfog", "fitting", "benchmarks", "helpers", "conftest", "make_mesh_fog"}


def _requirements(items) -> dict[str, str]:
    """`{"jax": ">=0.6.1", ...}` from requirement strings (lower-case names)."""
    out = {}
    for item in items:
        m = re.match(r"\s*([A-Za-z0-9_.\-]+)\s*(.*)", item)
        out[m.group(1).lower()] = m.group(2).strip()
    return out


def _imports(folder: str) -> set[str]:
    """Top-level names of every module imported anywhere (also inside functions) in `folder`'s .py files."""
    names = set()
    for path in (REPO / folder).rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                names |= {a.name.split(".")[0] for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names.add(node.module.split(".")[0])
    return {n for n in names if n not in sys.stdlib_module_names and n not in LOCAL and not n.startswith("test_")}


def _dist(name: str) -> str:
    return IMPORT_TO_DIST.get(name, name).lower()


def _version_tuple(text: str) -> tuple:
    return tuple(int(x) for x in re.findall(r"\d+", text)[:3])


def test_every_import_is_declared():
    deps = _requirements(PYPROJECT["project"]["dependencies"])
    extras = {k: _requirements(v) for k, v in PYPROJECT["project"]["optional-dependencies"].items()}
    library = {_dist(n) for n in _imports("jaxfog") | _imports("fitting")}
    missing = library - set(deps) - set(extras["compare"]) - set(extras["photo"])
    assert not missing, f"imported by jaxfog/ or fitting/ but not declared in dependencies: {sorted(missing)}"
    tests = {_dist(n) for n in _imports("tests")}
    missing = tests - set(deps) - set(extras["test"])
    assert not missing, f"imported by tests/ but declared neither in dependencies nor in the test extra: {sorted(missing)}"
    assert {"jaxtyping", "optimistix", "equinox", "jax"} <= set(deps)
    assert {"pytest", "scipy"} <= set(extras["test"]) and "scipy" not in deps  # scipy: tests only


def test_installed_versions_meet_the_floors():
    for name, spec in _requirements(PYPROJECT["project"]["dependencies"]).items():
        floor = re.match(r">=\s*([0-9.]+)", spec)
        if floor:
            have = importlib.metadata.version(name)
            assert _version_tuple(have) >= _version_tuple(floor.group(1)), (name, have, spec)


def test_jax_floor_has_shard_map_with_check_vma():
    """`jax.shard_map` with `check_vma` first appeared in jax 0.6.1 (checked in the wheels: 0.6.0 has neither the
    top-level `jax.shard_map` nor `check_vma`); the floor must be at least that, and the installed jax has it."""
    floor = _requirements(PYPROJECT["project"]["dependencies"])["jax"]
    assert _version_tuple(floor) >= (0, 6, 1), floor
    assert "check_vma" in inspect.signature(jax.shard_map).parameters
    assert "check_vma=" in (REPO / "jaxfog" / "_render.py").read_text()  # what the floor is for

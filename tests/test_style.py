"""The codebase stays ruff-clean (lint and format), checked where the tests run."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("args", [["check", "."], ["format", "--check", "."]])
def test_ruff_is_clean(args: list[str]) -> None:
    ruff = shutil.which("ruff")
    if ruff is None:
        pytest.skip("ruff is not installed (it comes with the 'test' extra)")
    result = subprocess.run([ruff, *args], cwd=ROOT, capture_output=True, text=True, check=False)
    assert result.returncode == 0, result.stdout + result.stderr


def test_imports_follow_the_layers() -> None:
    """import-linter's contract in pyproject.toml: each layer imports only from the layers below."""
    lint = shutil.which("lint-imports")
    if lint is None:
        pytest.skip("import-linter is not installed (it comes with the 'test' extra)")
    result = subprocess.run([lint], cwd=ROOT, capture_output=True, text=True, check=False)
    assert result.returncode == 0, result.stdout + result.stderr


def test_the_layers_contract_names_every_package() -> None:
    """A new package must be placed in a layer: one left out would escape the contract."""
    import tomllib

    layers = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"][0]
    named = {m.strip().removeprefix("orthonav.") for layer in layers["layers"] for m in layer.split("|")}
    package = ROOT / "src" / "orthonav"
    present = {p.parent.name for p in package.glob("*/__init__.py")} | {
        p.stem for p in package.glob("*.py") if p.stem != "__init__"
    }
    assert present == named, f"not in a layer: {sorted(present - named)}; gone: {sorted(named - present)}"


def _imported_modules(folder: Path) -> set[str]:
    """Top-level names of every module imported anywhere under ``folder`` (absolute imports)."""
    import ast

    names: set[str] = set()
    for path in folder.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names |= {alias.name.split(".")[0] for alias in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names.add(node.module.split(".")[0])
    return names


def _declared_distributions() -> set[str]:
    """Every distribution pyproject.toml names, base and extras, normalised (PEP 503); a
    requirement's own extras count too (``dask[distributed]`` is how distributed is asked for)."""
    import re
    import tomllib

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    requirements = list(project["dependencies"])
    for extra in project["optional-dependencies"].values():
        requirements += extra
    names = {re.split(r"[\s\[<>=!~;]", req, maxsplit=1)[0] for req in requirements}
    names |= {extra for req in requirements for extra in re.findall(r"[\[,]\s*([\w.-]+)", req)}
    return {re.sub(r"[-_.]+", "-", name).lower() for name in names}


@pytest.mark.parametrize("folder", ["src", "tests"])
def test_every_direct_import_is_declared(folder: str) -> None:
    """A module that arrives only through another package (affine through rasterio, pydantic
    through FastAPI) breaks the day that package drops it: each one imported is declared."""
    import re
    import sys
    from importlib.metadata import packages_distributions

    providers = packages_distributions()
    local = {p.stem for p in (ROOT / "tests").glob("*.py")} | {"orthonav"}
    missing = {}
    for module in _imported_modules(ROOT / folder) - set(sys.stdlib_module_names) - local:
        distributions = {re.sub(r"[-_.]+", "-", d).lower() for d in providers.get(module, [])}
        if module in providers and not distributions & _declared_distributions():
            missing[module] = sorted(distributions)
    assert not missing, f"imported but not declared in pyproject.toml: {missing}"

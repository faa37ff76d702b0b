"""Every benchmark's result file records what produced it: the CPU, the threads, the libraries'
versions, orthonav's own commit and the load (orthonav.bench.machine). A figure quoted without
them cannot be reproduced or compared with another machine's."""

from __future__ import annotations

import ast
import shutil
import subprocess
from pathlib import Path

import pytest

from orthonav.bench import machine
from orthonav.bench.machine import LoadWatch

BENCH = Path(__file__).resolve().parents[1] / "src" / "orthonav" / "bench"


def _benchmarks() -> list[tuple[str, ast.FunctionDef]]:
    found = []
    for path in sorted(BENCH.glob("*.py")):
        for node in ast.parse(path.read_text()).body:
            if (
                isinstance(node, ast.FunctionDef)
                and node.name.startswith("run_")
                and node.name.endswith("_benchmark")
            ):
                found.append((path.name, node))
    return found


@pytest.mark.parametrize("where, function", _benchmarks(), ids=lambda x: getattr(x, "name", x))
def test_every_benchmark_records_its_machine(where: str, function: ast.FunctionDef) -> None:
    keys = {
        key.value
        for node in ast.walk(function)
        if isinstance(node, ast.Dict)
        for key in node.keys
        if isinstance(key, ast.Constant)
    }
    calls = {
        node.func.id
        for node in ast.walk(function)
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name)
    }
    assert "machine" in keys and "LoadWatch" in calls, f"{where}: {function.name} writes no 'machine' record"


def test_the_benchmarks_are_found() -> None:
    assert len(_benchmarks()) >= 12


def test_the_record_names_the_code_it_ran(tmp_path: Path) -> None:
    """From a git checkout: the commit its sources came from and whether they differ from it; a
    copy outside any checkout (an installed package) records no commit rather than a wrong one."""
    record = LoadWatch().record()["orthonav"]
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=BENCH, capture_output=True, text=True)
    if head.returncode != 0 or Path(machine.__file__).resolve() != BENCH / "machine.py":
        pytest.skip("the package imported is not the sources of a git checkout")
    assert record["commit"] == head.stdout.strip() and isinstance(record["modified"], bool)
    assert record["version"]
    copy = tmp_path / "orthonav"
    shutil.copytree(BENCH.parent, copy, ignore=shutil.ignore_patterns("__pycache__"))
    assert not machine._git(copy, "ls-files", "--", "__init__.py")
    assert machine.code_version()["commit"] and not machine._git(copy, "rev-parse", "HEAD")

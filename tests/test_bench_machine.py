"""Every benchmark's result file records what produced it: the CPU, the threads, the libraries'
versions and the load (orthonav.bench.machine). A figure quoted without them cannot be reproduced
or compared with another machine's."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

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

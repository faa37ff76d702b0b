"""The result files the docs quote: each in docs/benchmarks/results/, each linked from a page (the
site's build refuses one that is not: docs/hooks.py)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

DOCS = Path(__file__).resolve().parents[1] / "docs"


def _hooks():
    spec = importlib.util.spec_from_file_location("docs_hooks", DOCS / "hooks.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _pages() -> list[str]:
    return [page.read_text() for page in DOCS.rglob("*.md")]


def test_every_result_file_is_linked_from_a_page() -> None:
    results = [str(p.relative_to(DOCS)) for p in (DOCS / "benchmarks" / "results").iterdir() if p.is_file()]
    assert len(results) > 100
    assert _hooks().unreferenced(results, _pages()) == []


def test_a_result_file_no_page_links_is_named() -> None:
    named = _hooks().unreferenced(
        [
            "benchmarks/results/bench_a.json",
            "benchmarks/results/bench_a.json.png",
            "benchmarks/results/b.png",
        ],
        ["[json](results/bench_a.json)", "![picture](benchmarks/results/b.png)"],
    )
    assert named == ["benchmarks/results/bench_a.json.png"]


def test_no_result_file_is_left_at_the_top_of_docs() -> None:
    left = [p.name for p in DOCS.glob("*") if p.suffix in {".json", ".png"} and p.name.startswith("bench_")]
    assert left == []

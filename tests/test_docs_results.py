"""The result files the docs quote: each in docs/benchmarks/results/, each linked from a page (the
site's build refuses one that is not: docs/hooks.py), and the figures tables of the README and the
pages written from them (docs/_figures.py), so that no two places disagree."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

DOCS = Path(__file__).resolve().parents[1] / "docs"


def _load(name: str):
    spec = importlib.util.spec_from_file_location(f"docs_{name}", DOCS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # a dataclass looks its module up there
    spec.loader.exec_module(module)
    return module


def _pages() -> list[str]:
    return [page.read_text() for page in DOCS.rglob("*.md")]


def test_every_result_file_is_linked_from_a_page() -> None:
    results = [str(p.relative_to(DOCS)) for p in (DOCS / "benchmarks" / "results").iterdir() if p.is_file()]
    assert len(results) > 100
    assert _load("hooks").unreferenced(results, _pages()) == []


def test_a_result_file_no_page_links_is_named() -> None:
    named = _load("hooks").unreferenced(
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


def test_the_committed_figures_are_the_result_files() -> None:
    """README.md and the pages carry the tables ``python docs/_figures.py`` writes from the results."""
    figures = _load("_figures")
    for page, prefix in figures.PAGES.items():
        text = page.read_text()
        assert "<!-- figures: " in text, page
        assert figures.fill(text, prefix) == text, f"{page}: run python docs/_figures.py"


def test_readme_and_overview_quote_the_same_headline_figures() -> None:
    figures = _load("_figures")
    readme, overview = (figures.BLOCK.search(page.read_text()) for page in list(figures.PAGES)[:2])
    assert readme["body"].replace("docs/benchmarks/results/", "results/") == overview["body"]


def test_readme_starts_with_the_two_commands() -> None:
    readme = (DOCS.parent / "README.md").read_text().splitlines()
    assert readme[:4] == [
        "```bash",
        "pip install . && orthonav demo",
        'pip install -e ".[test]" && python -m pytest -q',
        "```",
    ]


def test_a_sitl_flight_with_parameters_over_its_scenario_says_which() -> None:
    """Such a flight is not the scenario as coded: its row must not pass for it."""
    figures = _load("_figures")
    rows = [{"name": "copter-gnss-off-flow", "failsafes": ["EKF3 lane switch 1"]}]
    tuned = {"config": {"hfov_deg": 90.0, "extra_params": [["EK3_POSNE_M_NSE", 25.0]]}, "rows": rows}
    ((label, row),) = figures._sitl_rows(tuned)
    assert label == "`copter-gnss-off-flow`, 90 deg lens, `EK3_POSNE_M_NSE 25`"
    assert row["lane_switches"] == 1 and not row["ekf_failsafe"]
    for config in ({"hfov_deg": 60.0}, {"hfov_deg": 60.0, "extra_params": []}):
        assert figures._sitl_rows({"config": config, "rows": rows})[0][0] == "`copter-gnss-off-flow`"

"""MkDocs hooks: put docs/ on ``sys.path`` so that mkdocs-click can import ``_cli`` (the CLI reference), fill
each page's figures tables from the result files (``_figures``), and refuse a result file in
``benchmarks/results/`` that no page links to (a figure nobody can find is not a result)."""

from __future__ import annotations

import logging
import posixpath
import re
import sys
from collections.abc import Iterable
from pathlib import Path

DOCS_DIR = str(Path(__file__).resolve().parent)
RESULTS_DIR = "benchmarks/results/"

# A logger under "mkdocs": its warnings fail `mkdocs build --strict`.
log = logging.getLogger("mkdocs.hooks.results")


def on_config(config):
    if DOCS_DIR not in sys.path:
        sys.path.insert(0, DOCS_DIR)
    return config


def on_files(files, config):
    results = [f.src_uri for f in files if _is_result(f.src_uri)]
    pages = [f.content_string for f in files if f.is_documentation_page()]
    for name in unreferenced(results, pages):
        log.warning("%s is linked from no page: link it where its figures are quoted, or delete it", name)
    return files


def on_page_markdown(markdown, page, config, files):
    import _figures  # docs/, on sys.path since on_config

    prefix = posixpath.relpath(RESULTS_DIR, posixpath.dirname(page.file.src_uri) or ".")
    return _figures.fill(markdown, prefix + "/")


def unreferenced(results: Iterable[str], pages: Iterable[str]) -> list[str]:
    """The result files (paths under docs/) whose ``results/NAME`` appears in none of the pages' text."""
    text = "\n".join(pages)
    return [
        name
        for name in sorted(results)
        if not re.search(r"results/" + re.escape(Path(name).name) + r"(?![\w.-])", text)
    ]


def _is_result(src_uri: str) -> bool:
    """A file directly in the results folder (a benchmark's own run folders beside it are not results)."""
    return src_uri.startswith(RESULTS_DIR) and "/" not in src_uri[len(RESULTS_DIR) :]

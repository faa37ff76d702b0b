"""MkDocs hook: put docs/ on ``sys.path`` so that mkdocs-click can import ``_cli`` (the CLI reference)."""

from __future__ import annotations

import sys
from pathlib import Path

DOCS_DIR = str(Path(__file__).resolve().parent)


def on_config(config):
    if DOCS_DIR not in sys.path:
        sys.path.insert(0, DOCS_DIR)
    return config

"""The ``orthonav`` command as a click command, for mkdocs-click (docs/cli.md).

The CLI is a typer app (``orthonav.cli.main:app``); ``typer.main.get_command`` turns it into
the click command tree that mkdocs-click walks. Default paths are relative to where a command
runs (the shared data set as ``../shared/data/...``), so the reference shows them as a user types
them on any machine.
"""

from __future__ import annotations

import typer

from orthonav.cli.main import app

cli = typer.main.get_command(app)

"""The ``orthonav`` command as a click command, for mkdocs-click (docs/cli.md).

The CLI is a typer app (``orthonav.cli.main:app``); ``typer.main.get_command`` turns it into
the click command tree that mkdocs-click walks. Default paths are relative to where a command
runs (the shared data set as ``../shared/data/...``), so the reference shows them as a user types
them on any machine.

Two things typer's terminal help does that a page does not: it reads help texts as rich markup
(so a literal bracket is written ``\\[``), and it joins a docstring's first paragraph into the
command's summary where mkdocs-click keeps only its first line. Both are undone here.
"""

from __future__ import annotations

from typing import Any

import typer

from orthonav.cli.main import app


def _as_page(command: Any) -> None:
    """Help texts of ``command`` and everything under it as plain text, each summary whole."""
    if command.help:
        command.help = command.help.replace("\\[", "[")
        if not command.short_help:
            command.short_help = " ".join(command.help.split("\n\n")[0].split())
    for param in command.params:
        if getattr(param, "help", None):
            param.help = param.help.replace("\\[", "[")
    for sub in getattr(command, "commands", {}).values():
        _as_page(sub)


cli = typer.main.get_command(app)
_as_page(cli)

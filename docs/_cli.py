"""The ``orthonav`` command as a click command, for mkdocs-click (docs/cli.md).

The CLI is a typer app (``orthonav.cli.main:app``); ``typer.main.get_command`` turns it into
the click command tree that mkdocs-click walks. Defaults that are absolute paths on the machine
building the docs (the shared data folder next to the project) are shown relative to the
project root instead, as a user would type them.
"""

from __future__ import annotations

from pathlib import Path

import typer

from orthonav.cli.main import app

PROJECT_ROOT = Path(__file__).resolve().parent.parent


def _display_path(value: object) -> object:
    """An absolute path inside the project or beside it, as a path relative to the project root."""
    if not isinstance(value, Path) or not value.is_absolute():
        return value
    for base, prefix in ((PROJECT_ROOT, Path()), (PROJECT_ROOT.parent, Path(".."))):
        if value.is_relative_to(base):
            return prefix / value.relative_to(base)
    return value


def _relative_defaults(command) -> None:
    """Walk the command tree (typer's commands are click commands, possibly typer's own copy of click)."""
    for param in command.params:
        param.default = _display_path(param.default)
    for sub in getattr(command, "commands", {}).values():
        _relative_defaults(sub)


cli = typer.main.get_command(app)
_relative_defaults(cli)

"""What ``--help`` and the rendered CLI reference say: labels a shell user reads (no Python types,
no braces), words a UAV engineer can decode, and summaries whole."""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path
from typing import Any

import pytest
import typer
from typer.testing import CliRunner

from orthonav.cli.main import app

runner = CliRunner()
DOCS_CLI = Path(__file__).resolve().parents[1] / "docs" / "_cli.py"
# Words of the code base that mean nothing to someone who did not write it.
JARGON = re.compile(r"seed 0\d|trained trunk|graph version|descriptors first", re.IGNORECASE)


def commands(command: Any = None, path: tuple[str, ...] = ()) -> list[tuple[tuple[str, ...], Any]]:
    """Every command and group of the CLI with its argument path."""
    command = command or typer.main.get_command(app)
    found = [(path, command)]
    for name, sub in getattr(command, "commands", {}).items():
        found += commands(sub, (*path, name))
    return found


@pytest.mark.parametrize("path", [path for path, _ in commands()], ids=lambda p: " ".join(p) or "orthonav")
def test_help_labels_values_for_the_shell(path: tuple[str, ...]) -> None:
    """A flag takes no value, a repeatable option one path at a time, an argument is NAME."""
    result = runner.invoke(app, [*path, "--help"], env={"COLUMNS": "200"})
    assert result.exit_code == 0, result.output
    assert "<bool>" not in result.output
    assert "list[" not in result.output
    usage = next(line for line in result.output.splitlines() if "Usage:" in line)
    assert "{" not in usage, usage


def test_help_labels_of_the_issue() -> None:
    fly = runner.invoke(app, ["fly", "--help"], env={"COLUMNS": "200"}).output
    assert re.search(r"--fallback\s+<path>", fly), fly
    assert re.search(r"--help\s+Show this message", fly), fly
    build = runner.invoke(app, ["map", "build", "--help"], env={"COLUMNS": "200"}).output
    assert "map build [OPTIONS] ORTHO" in build


def test_help_has_no_jargon() -> None:
    """Every help text, the command's and its parameters', in words of the trade."""
    for path, command in commands():
        texts = [command.help or "", *(getattr(param, "help", "") or "" for param in command.params)]
        for text in texts:
            assert not JARGON.search(text), (" ".join(path), text)


def test_rendered_reference_is_plain_text_with_whole_summaries() -> None:
    """mkdocs-click shows a summary's first line and help as written: no rich-markup escapes, and
    the odometry summary not cut at its line break."""
    spec = importlib.util.spec_from_file_location("docs_cli", DOCS_CLI)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    for path, command in commands(module.cli):
        texts = [command.help or "", *(getattr(param, "help", "") or "" for param in command.params)]
        assert not any("\\[" in text for text in texts), path
    odometry = module.cli.commands["odometry"]
    assert odometry.short_help.splitlines()[0].endswith("base viewpoint)."), odometry.short_help
    build = module.cli.commands["map"].commands["build"]
    assert any("orthonav[scale]" in (param.help or "") for param in build.params)

"""Default paths of the commands: relative to where the command runs, as the CLI reference says,
never computed from the installed package's location (inside the environment after
``pip install .``)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import typer
from typer.testing import CliRunner

from orthonav.cli.main import app
from orthonav.errors import OrthonavError


def path_defaults(command: Any, prefix: str = "orthonav") -> list[tuple[str, Path]]:
    """(command and parameter, default) for every default path in ``command``'s tree (a click
    command, as typer builds it)."""
    found = []
    for param in command.params:
        values = param.default if isinstance(param.default, list | tuple) else [param.default]
        found += [(f"{prefix} {param.name}", value) for value in values if isinstance(value, Path)]
    for name, sub in getattr(command, "commands", {}).items():
        found += path_defaults(sub, f"{prefix} {name}")
    return found


def test_no_default_path_is_absolute() -> None:
    defaults = path_defaults(typer.main.get_command(app))
    assert any(str(value).startswith("../shared/data") for _, value in defaults)
    assert [(where, value) for where, value in defaults if value.is_absolute()] == []


def test_bench_real_away_from_the_project_root_names_the_folder_to_pass(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    result = CliRunner().invoke(app, ["bench", "real", "--out", str(tmp_path / "out.json")])
    assert isinstance(result.exception, OrthonavError), result.output
    message = str(result.exception)
    assert message.startswith("../shared/data/real/seneca: no such dataset folder (pass DATASET")
    assert "\n" not in message

"""One name per concept across the commands, a version, coordinates that may be negative, and
extras named in help and errors."""

from __future__ import annotations

from importlib.metadata import version

import pytest
import typer
from rich.console import Console
from typer.testing import CliRunner

from orthonav.cli import output
from orthonav.cli.main import app
from orthonav.errors import OrthonavError
from orthonav.mapdb import MapPackage

runner = CliRunner()
# Names that once meant the same thing as another option somewhere else.
RETIRED = {
    "--prior-lat",
    "--prior-lon",
    "--lat",
    "--lon",
    "--sigma",
    "--alt",
    "--backend",
    "--camera-json",
    "--fps",
}


def all_options() -> dict[str, list[tuple[str, str]]]:
    """Every long option: {name: [(command path, help text)]}."""
    found: dict[str, list[tuple[str, str]]] = {}

    def walk(command, path: str) -> None:
        for name, sub in getattr(command, "commands", {}).items():
            walk(sub, f"{path} {name}".strip())
        for param in command.params:
            for opt in (o for o in param.opts if o.startswith("--")):
                found.setdefault(opt, []).append((path, getattr(param, "help", "") or ""))

    walk(typer.main.get_command(app), "")
    return found


def test_one_name_per_concept() -> None:
    options = all_options()
    assert not RETIRED & set(options), sorted(RETIRED & set(options))
    # --camera is always the camera JSON (frames come with --frames).
    for path, help_text in options["--camera"]:
        assert "camera json" in help_text.lower(), (path, help_text)
    for path, help_text in options.get("--prior", []):
        assert "LAT,LON" in help_text, (path, help_text)


def test_version() -> None:
    result = runner.invoke(app, ["--version"])
    assert result.exit_code == 0 and result.stdout.strip() == f"orthonav {version('orthonav')}"


def test_negative_coordinates_are_values_not_options(terrain_map: MapPackage, tmp_path) -> None:
    """South and west are negative: '--start -33.5,151.2' reaches the command (here: off the map)."""
    args = ["simulate", str(terrain_map.path), "--start", "-33.5,151.2", "--target", "-33.4,151.3"]
    result = runner.invoke(app, [*args, "--out", str(tmp_path)])
    assert isinstance(result.exception, OrthonavError), result.output
    assert "outside the map" in str(result.exception)


@pytest.mark.parametrize(("command", "extra"), [(["map", "build", "--help"], "orthonav[scale]")])
def test_help_names_the_extra(command: list[str], extra: str) -> None:
    result = runner.invoke(app, command, env={"COLUMNS": "200"})
    assert result.exit_code == 0 and extra in result.stdout


def test_ctrl_c_says_what_is_kept_and_exits_130(terrain_tif, tmp_path, monkeypatch, capsys) -> None:
    """typer turns Ctrl-C into exit code 130 on its own; the entry point still says what is kept."""
    import sys

    import orthonav.mapdb
    from orthonav.cli.main import main

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(orthonav.mapdb, "build_map", interrupted)
    monkeypatch.setattr(
        sys, "argv", ["orthonav", "map", "build", str(terrain_tif), "--out", str(tmp_path / "m")]
    )
    with pytest.raises(SystemExit) as exit_info:
        main()
    assert exit_info.value.code == 130
    assert "interrupted: results written so far are kept" in capsys.readouterr().err


def test_a_table_too_wide_wraps_its_headers_between_words(monkeypatch) -> None:
    """Every column name reaches the console whole, on more lines where narrow: between its words
    (not 'fix_sourc' over 'e') where they fit, folded where even they do not. It is the key to
    look the value up in the JSON; no value is cut either."""
    row = {"placed_centre_within_10m": 0.875, "centre_within_10m": 0.8, "false_25m_rate": 0.0}
    row |= {"median_total_ms": 85.2, "frames_from": "m_14_1_20120731", "condition": "cross-date"}
    row |= {"fix_source": "cascade", "variant": "dsm+att"}
    for width in (60, 100):
        narrow = Console(width=width, record=True)
        monkeypatch.setattr(output, "table_console", narrow)
        output.print_rows("narrow", [row])
        lines = narrow.export_text().splitlines()[1:]  # under the title
        header = lines[: next(i for i, line in enumerate(lines) if "0.875" in line)]
        assert "…" not in narrow.export_text()
        letters = sum(len(key.replace("_", "")) for key in row)
        assert sum(len(line.replace(" ", "")) for line in header) == letters
        if width == 100:
            for word in {word for key in row for word in key.split("_")}:
                assert any(word in line for line in header), (word, header)

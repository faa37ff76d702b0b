"""``orthonav``: the command-line application, its command groups and its entry point."""

from __future__ import annotations

import logging
import signal
import sys
from importlib.metadata import version
from types import FrameType
from typing import Annotated, NoReturn

import typer
from rich.markup import escape

from orthonav.atomic import file_error
from orthonav.cli.bench import bench_app
from orthonav.cli.correction import correction_app
from orthonav.cli.fly import fly
from orthonav.cli.helptext import label_parameters
from orthonav.cli.localize import localize
from orthonav.cli.maps import map_app
from orthonav.cli.mission import demo, simulate
from orthonav.cli.models import models_app
from orthonav.cli.odometry import odometry
from orthonav.cli.output import err_console
from orthonav.cli.replay import replay
from orthonav.cli.serve import serve
from orthonav.cli.slam import slam
from orthonav.cli.vehicle import sim_vehicle
from orthonav.errors import OrthonavError

app = typer.Typer(
    help="Map-based optical navigation for drones without GNSS.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
)
# Help grouped by workflow, in the order a user meets them.
app.add_typer(map_app, name="map", rich_help_panel="Map")
app.add_typer(models_app, name="models", rich_help_panel="Map")
app.command(rich_help_panel="Localize")(localize)
app.add_typer(correction_app, name="correction", rich_help_panel="Localize")
app.command(rich_help_panel="Simulate")(demo)
app.command(rich_help_panel="Simulate")(simulate)
app.command("sim-vehicle", rich_help_panel="Simulate")(sim_vehicle)
app.command(rich_help_panel="Simulate")(slam)
app.command(rich_help_panel="Fly")(fly)
app.command(rich_help_panel="Replay")(replay)
app.command(rich_help_panel="Replay")(odometry)
app.command(rich_help_panel="Serve")(serve)
app.add_typer(bench_app, name="bench", rich_help_panel="Bench")
label_parameters(app)


def _print_version(value: bool) -> None:
    if value:
        typer.echo(f"orthonav {version('orthonav')}")
        raise typer.Exit()


@app.callback()
def _options(
    show_version: Annotated[
        bool,
        typer.Option("--version", help="Print the version and exit.", callback=_print_version, is_eager=True),
    ] = False,
) -> None:
    """Map-based optical navigation for drones without GNSS."""


def main() -> None:
    """Console entry point: user errors and file system errors (an output that cannot be
    written) become one clear line and exit code 2."""
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    # Past the file size limit (ulimit -f) the kernel's SIGXFSZ would kill the process without a
    # word; ignored, the write fails with EFBIG and is reported as any full output is.
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    # SIGTERM (a service manager, `kill`, a closed CI job) ends any command as Ctrl-C does: what
    # was written is kept and the interruption said in one line, not lost silently. fly and serve
    # put their own stop in its place while they run.
    signal.signal(signal.SIGTERM, _interrupt)
    try:
        app()
    except OrthonavError as exc:
        _say_error(str(exc))
    except OSError as exc:
        _say_error(file_error(exc))
    except KeyboardInterrupt:
        _say_interrupted()
        sys.exit(130)
    except SystemExit as exc:  # typer turns Ctrl-C into exit code 130 before it reaches us
        if _caused_by_interrupt(exc):
            _say_interrupted()
        raise


def _interrupt(signum: int, frame: FrameType | None) -> NoReturn:
    raise KeyboardInterrupt


def _say_error(message: str) -> NoReturn:
    # One line whatever the terminal width; the message is text, not rich markup.
    err_console.print(f"[bold red]error:[/] {escape(message)}", highlight=False, soft_wrap=True)
    sys.exit(2)


def _say_interrupted() -> None:
    err_console.print("interrupted: results written so far are kept (a map build resumes when rerun)")


def _caused_by_interrupt(exc: BaseException) -> bool:
    """Whether a KeyboardInterrupt is in the chain of exceptions that led to ``exc``."""
    seen: set[int] = set()
    current: BaseException | None = exc
    while current is not None and id(current) not in seen:
        if isinstance(current, KeyboardInterrupt):
            return True
        seen.add(id(current))
        current = current.__cause__ or current.__context__
    return False


if __name__ == "__main__":
    main()

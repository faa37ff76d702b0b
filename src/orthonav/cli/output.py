"""What the commands print: tables that stay readable when piped, and the shared consoles."""

from __future__ import annotations

from collections.abc import Sequence

from rich.console import Console
from rich.table import Table
from rich.text import Text

from orthonav.errors import OrthonavError
from orthonav.localize.sources import OpenedFixSource

console = Console()
err_console = Console(stderr=True)
# Tables stay readable when piped to a file (rich would wrap them at 80 columns).
table_console = console if console.is_terminal else Console(width=160)


def say(lines: Sequence[str], style: str = "") -> None:
    """Lines for the user on stderr, as they are: no markup read into them, nothing highlighted."""
    for line in lines:
        err_console.print(Text(line, style=style), highlight=False, soft_wrap=True)


def say_fix_source(opened: OpenedFixSource) -> None:
    """Which fix source runs; where it is not the one asked for (the default's fallback), why,
    as a warning."""
    if opened.fallback:
        say([opened.fallback], "yellow")
    say([opened.description])


def print_dict(title: str, data: dict) -> None:
    """A key-value table, a nested dict's keys under its own (``link packets_sent``); numbers
    in short form, as the JSON keeps them in full."""
    table = Table(title=title, show_header=False)
    for key, value in _flat(data):
        table.add_row(Text(key), Text(value if isinstance(value, str) else number(value)))
    table_console.print(table)


def _flat(data: dict, prefix: str = "") -> list[tuple[str, object]]:
    rows: list[tuple[str, object]] = []
    for key, value in data.items():
        if isinstance(value, dict):
            rows += _flat(value, f"{prefix}{key} ")
        else:
            rows.append((f"{prefix}{key}", value))
    return rows


def print_rows(title: str, rows: list[dict]) -> None:
    """One row per dict, the first dict's keys as columns (list-valued columns left out). A header
    too long for its column wraps between the words of its name (its underscores shown as
    spaces); where even the longest words do not fit side by side they fold, and values fold
    too: nothing is cut, the name is the key to the JSON."""
    if not rows:
        return
    table = Table(title=title, box=None)
    keys = [k for k in rows[0] if not isinstance(rows[0][k], list)]
    words = [max(len(word) for word in key.split("_")) for key in keys]
    fits = sum(words) + 2 * len(keys) <= table_console.width  # each column padded by one a side
    for key, word in zip(keys, words, strict=True):
        header = Text(key.replace("_", " "), overflow="fold")
        table.add_column(header, justify="right", overflow="fold", min_width=word if fits else None)
    for row in rows:
        table.add_row(*(cell(row.get(k)) for k in keys))
    table_console.print(table)


def cell(value: object) -> str:
    """A table cell: numbers in short form, dated file names as their date."""
    if isinstance(value, str):
        return value[-8:] if value[-8:].isdigit() else value
    return number(value)


def number(value: object) -> str:
    """A value as a person reads it: six significant digits, counts whole, yes/no, '-' for none."""
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return f"{value:.6g}" if abs(value) < 1e6 else f"{value:.0f}"
    return str(value)


def csv_values(text: str, option: str, kind: type = str) -> tuple:
    """Comma-separated values of one type, at least one, or an error naming the option."""
    try:
        values = tuple(kind(v.strip()) for v in text.split(",") if v.strip())
    except ValueError:
        raise OrthonavError(f"{option} {text!r}: expected comma-separated {kind.__name__} values") from None
    if not values:
        raise OrthonavError(f"{option}: expected at least one value")
    return values

"""What the commands print: tables that stay readable when piped, and the shared consoles."""

from __future__ import annotations

from rich.console import Console
from rich.table import Table
from rich.text import Text

from orthonav.errors import OrthonavError

console = Console()
err_console = Console(stderr=True)
# Tables stay readable when piped to a file (rich would wrap them at 80 columns).
table_console = console if console.is_terminal else Console(width=160)


def print_dict(title: str, data: dict) -> None:
    """A key-value table."""
    table = Table(title=title, show_header=False)
    for key, value in data.items():
        table.add_row(str(key), str(value))
    table_console.print(table)


def print_rows(title: str, rows: list[dict]) -> None:
    """One row per dict, the first dict's keys as columns (list-valued columns left out). A header
    too long for its column folds onto more lines rather than being cut: the name is the key to
    the JSON."""
    if not rows:
        return
    table = Table(title=title, box=None)
    keys = [k for k in rows[0] if not isinstance(rows[0][k], list)]
    for key in keys:
        table.add_column(Text(key, overflow="fold"), justify="right")
    for row in rows:
        table.add_row(*(cell(row.get(k)) for k in keys))
    table_console.print(table)


def cell(value: object) -> str:
    """A table cell: numbers in short form, dated file names as their date."""
    if value is None:
        return "-"
    if isinstance(value, str):
        return value[-8:] if value[-8:].isdigit() else value
    if isinstance(value, bool):
        return "yes" if value else "no"
    return f"{value:g}"


def csv_values(text: str, option: str, kind: type = str) -> tuple:
    """Comma-separated values of one type, at least one, or an error naming the option."""
    try:
        values = tuple(kind(v.strip()) for v in text.split(",") if v.strip())
    except ValueError:
        raise OrthonavError(f"{option} {text!r}: expected comma-separated {kind.__name__} values") from None
    if not values:
        raise OrthonavError(f"{option}: expected at least one value")
    return values

"""One error type for every input the user can get wrong.

The CLI turns an :class:`OrthonavError` into a one-line message naming the file or field
and what was expected; anything else is a bug and keeps its traceback.
"""

import json
import math
from pathlib import Path
from typing import Any


class OrthonavError(ValueError):
    """Bad input (file, field or parameter), with a message a user can act on."""


def require_positive(what: str, owner: object, names: tuple[str, ...]) -> None:
    """Each named field of ``owner`` is a finite number > 0; else an error naming ``what name``."""
    for name in names:
        value = getattr(owner, name)
        if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
            raise OrthonavError(f"{what} {name}: expected a positive number, got {value}")


def beyond(value: float, limit: float, decimals: int = 1) -> str:
    """``value`` printed with as many decimals as it takes to differ from ``limit`` printed the
    same way, so that a rejection never reads "2.0 above 2.0"."""
    for d in range(decimals, 7):
        text, bound = f"{value:.{d}f}", f"{limit:.{d}f}"
        if text != bound:
            return text
    return f"{value:g}"


def read_json_file(path: Path, what: str) -> Any:
    """The JSON in the user's file ``path`` (``what`` it should be, for the message), read as
    UTF-8 with or without the byte order mark editors on Windows write; every way it cannot be
    read is one error naming the file."""
    try:
        text = path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise OrthonavError(f"{path}: no such {what}") from None
    except UnicodeDecodeError:
        raise OrthonavError(f"{path}: not a text file ({what} in JSON expected)") from None
    except OSError as exc:
        raise OrthonavError(f"{path}: cannot read the {what} ({exc.strerror or exc})") from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise OrthonavError(f"{path}: not valid JSON ({what} expected; {exc})") from None

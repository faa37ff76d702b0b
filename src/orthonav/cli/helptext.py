"""How ``--help`` names the values options and arguments take.

typer labels every option with its Python type: a flag reads ``--json <bool>`` as if it took a
value, a repeatable option ``--fallback <list[Path]>``, and a required argument is written
``{ortho}`` in the usage line. The classes here keep typer's rendering and give each parameter
the label a shell user expects: nothing after a flag, the element's type after a repeatable
option (its help says it repeats), and ``ORTHO`` / ``[DATASET]`` for arguments.
"""

from __future__ import annotations

import re
from typing import Any

import typer
from typer.core import TyperArgument, TyperCommand, TyperGroup, TyperOption

_LIST_LABEL = re.compile(r"<list\[(.+)\]>")


def _label(param: Any, ctx: Any) -> None:
    """Set ``param``'s metavar once (the parameters live as long as the command)."""
    if param.metavar is not None:
        return
    if isinstance(param, TyperArgument):
        param.metavar = (param.name or "").upper()
    elif getattr(param, "is_flag", False) or getattr(param, "count", False):
        param.metavar = ""
    elif isinstance(param, TyperOption) and param.multiple:
        shown = _LIST_LABEL.fullmatch(param.display_type(ctx))
        if shown:
            param.metavar = f"<{shown[1].lower()}>"


class _Labelled:
    """Parameters labelled as :func:`_label` says; arguments in the usage line without braces.
    (typer's commands are classes of the click it ships; typed loosely so as not to import it.)"""

    def get_params(self, ctx: Any) -> list[Any]:
        params = super().get_params(ctx)
        for param in params:
            _label(param, ctx)
        return params

    def collect_usage_pieces(self, ctx: Any) -> list[str]:
        plain = {
            piece: _usage(param)
            for param in self.get_params(ctx)
            if isinstance(param, TyperArgument)
            for piece in param.get_usage_pieces(ctx)
        }
        return [plain.get(piece, piece) for piece in super().collect_usage_pieces(ctx)]


def _usage(argument: TyperArgument) -> str:
    name = argument.metavar or (argument.name or "").upper()
    name = name if argument.required else f"[{name}]"
    return f"{name}..." if argument.nargs != 1 else name


class LabelledCommand(_Labelled, TyperCommand):
    """A command whose help labels its parameters for the shell."""


class LabelledGroup(_Labelled, TyperGroup):
    """A command group whose help labels its parameters for the shell."""


def label_parameters(app: typer.Typer) -> None:
    """Make ``app``, its commands and its groups, recursively, render their help with the labelled
    classes (typer builds the click commands from these settings each time it runs)."""
    app.info.cls = LabelledGroup
    for command in app.registered_commands:
        if command.cls in (None, TyperCommand):
            command.cls = LabelledCommand
    for group in app.registered_groups:
        group.cls = LabelledGroup
        if group.typer_instance is not None:
            label_parameters(group.typer_instance)

"""The console of the command line and the demo: rich's when the ``cli`` extra is installed, else plain
``print`` with rich's markup tags dropped (tables are then passed in as text); the robot-option rule the
subcommands share (:func:`check_one_robot`)."""

from __future__ import annotations

import re

from .errors import DiffkinError

__all__ = ["console", "check_one_robot"]

_MARKUP = re.compile(r"\[/?(?:green|red|bold|yellow|dim)\]")


class PlainConsole:
    """``print`` for what would go to rich's console: the markup tags this package uses are removed."""

    @staticmethod
    def print(obj="", **_kwargs) -> None:
        print(_MARKUP.sub("", str(obj)))


def console():
    """rich's ``Console(highlight=False)``, or a :class:`PlainConsole` without rich."""
    try:
        from rich.console import Console
    except ImportError:
        return PlainConsole()
    return Console(highlight=False)


def check_one_robot(args) -> None:
    """At most one of ``--robot``, ``--urdf``, ``--mjcf``: two are a :class:`DiffkinError` naming them (one
    of them would otherwise be silently ignored)."""
    given = [f"--{flag}" for flag in ("robot", "urdf", "mjcf") if getattr(args, flag, None)]
    if len(given) > 1:
        raise DiffkinError(f"give the robot once: {' and '.join(given)} were both given (--robot "
                           "NAME|FILE.yaml, --urdf FILE or --mjcf FILE, with --end-link for a file)")

"""The console of the command line and the demo: rich's when the ``cli`` extra is installed, else plain
``print`` with rich's markup tags dropped (tables are then passed in as text)."""

from __future__ import annotations

import re

__all__ = ["console"]

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

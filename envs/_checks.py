"""Checks of the envs' numeric settings (no env imports: every env module may use them)."""

from __future__ import annotations

import math

from diffkin.errors import DiffkinError


def check_setting(value, name: str, *, low: float | None = None, high: float | None = None,
                  strict_low: bool = False, integer: bool = False) -> None:
    """A numeric setting of an env config: a finite number (an integer where ``integer``) in its range."""
    kind = int if integer else (int, float)
    ok = isinstance(value, kind) and not isinstance(value, bool) and math.isfinite(value)
    if ok and low is not None:
        ok = value > low if strict_low else value >= low
    if ok and high is not None:
        ok = value <= high
    if not ok:
        rng = "" if low is None else f" {'>' if strict_low else '>='} {low}"
        rng += "" if high is None else f"{',' if rng else ''} <= {high}"
        what = "an integer" if integer else "a finite number"
        raise DiffkinError(f"expected {name} as {what}{rng}, got {value!r}")

"""Fuzz cases of the robot-level API: chains, models, redundancy (the pinv family), ik
(see ``tests/fuzzing.py`` for the format)."""

from __future__ import annotations

from tests.fuzzing import Case

#: modules whose every public callable must have a case or an exemption
MODULES: list[str] = []
CASES: list[Case] = []
#: public callables without a case, with the reason
EXEMPT: dict[str, str] = {}

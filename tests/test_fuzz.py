"""Fuzz suite (hypothesis): every public function, with bad shapes, dtypes, NaN/inf, empty and numpy input,
gives the typed error or the correct result the shared validators promise (see ``tests/fuzzing.py``)."""

from __future__ import annotations

import importlib
import inspect

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from tests import (
    fuzz_cases_calibration,
    fuzz_cases_geometry,
    fuzz_cases_io,
    fuzz_cases_robots,
    fuzz_cases_viz,
)
from tests.fuzzing import mutations, outcome

_FILES = (fuzz_cases_geometry, fuzz_cases_robots, fuzz_cases_calibration, fuzz_cases_io, fuzz_cases_viz)
CASES = {c.name: c for f in _FILES for c in f.CASES}
EXEMPT = {k: v for f in _FILES for k, v in f.EXEMPT.items()}
MODULES = [m for f in _FILES for m in f.MODULES]

PARAMS = [(name, m) for name, case in CASES.items() for m in mutations(case)]
#: the suite's hang guard (pyproject's ``timeout``) by the thread method, since the harness's own per-call
#: guard uses SIGALRM; neither is a time limit a real call comes near (tests check results, not time)
pytestmark = pytest.mark.timeout(method="thread")


def _public_callables(module_name: str) -> dict[str, object]:
    module = importlib.import_module(module_name)
    out = {}
    for attr in getattr(module, "__all__", []):
        obj = getattr(module, attr)
        if inspect.isfunction(obj) or (inspect.isclass(obj) and not issubclass(obj, BaseException)):
            out[f"{module_name}.{attr}"] = obj
    return out


@pytest.mark.parametrize("module_name", MODULES)
def test_every_public_function_is_fuzzed_or_exempt(module_name):
    """A public callable has a case (under any module that re-exports it) or a stated reason not to."""
    fuzzed = {id(c.target) for c in CASES.values()}
    exempt = {id(obj) for name, obj in _all_public().items() if name in EXEMPT}
    missing = [n for n, obj in _public_callables(module_name).items() if id(obj) not in fuzzed | exempt]
    assert not missing, f"public callables without a fuzz case or a stated exemption: {missing}"


def _all_public() -> dict[str, object]:
    return {n: o for m in MODULES for n, o in _public_callables(m).items()}


@pytest.mark.parametrize(("name", "mutation"), PARAMS, ids=[f"{n}[{m}]" for n, m in PARAMS])
@settings(max_examples=2, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2**16), double=st.booleans())
def test_typed_error_or_correct_result(name, mutation, seed, double):
    kind, detail = outcome(CASES[name], mutation, seed, torch.float64 if double else torch.float32,
                           time_limit=600.0)  # a hang guard per call, far above any real one
    assert kind in ("typed", "correct"), f"{name} [{mutation}]: {kind}: {detail}"


_SETTINGS = test_typed_error_or_correct_result._hypothesis_internal_use_settings


@pytest.fixture(autouse=True)
def _flat_hypothesis_settings():
    """hypothesis' pytest plugin (6.170) gives each parametrized item a settings object whose parent is the
    previous item's, so the parent chain grows by one per item and overflows the recursion limit after about
    950 items (RecursionError in ``settings.database``): start every item from the decorator's settings."""
    test_typed_error_or_correct_result._hypothesis_internal_use_settings = _SETTINGS

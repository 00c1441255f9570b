"""The fuzz harness: each public function, declared once as a :class:`Case`, is called with bad input of every
class the shared validators (``diffkin.validation``) promise to catch, and with the good-input variants they
promise to accept.

A :class:`Case` names the function's arguments in order, each with how to build a valid value for a batch
shape and dtype (:class:`Arg`). The mutations below change one argument at a time and state what must follow:

=============  ============================================  ============================================
mutation       input                                         expected
=============  ============================================  ============================================
``nan``        one entry NaN                                 ``NonFiniteError``
``inf``        one entry ±inf                                ``NonFiniteError``
``shape``      a trailing dimension one too large / missing  ``ShapeError``
``dtype:X``    the argument cast to int64, bool, complex64,  ``DTypeError``
               float16 or bfloat16
``mixed``      the argument in the other float dtype         ``DTypeError``
``numpy``      the argument as a numpy array                 the same result as with the tensor
``empty``      every batched argument with batch (0,)        a result whose batch dims are (0,) (or the
                                                             case's ``empty_raises`` error, where an
                                                             empty batch cannot have a result)
``valid``      random valid input                            a finite result with the right batch dims
=============  ============================================  ============================================

:func:`outcome` classifies one call — ``typed`` (the promised error), ``correct`` (the promised result),
``silent`` (a wrong result, NaN/inf out, or no error where one was promised), ``crash`` (any other
exception) or ``hang`` (over the time limit) — for ``tests/test_fuzz.py`` and for the sweep counts
(``python -m tests.fuzzing``).
"""

from __future__ import annotations

import math
import signal
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

from diffkin.errors import DiffkinError, DTypeError, NonFiniteError, ShapeError

BAD_DTYPES = (torch.int64, torch.bool, torch.complex64, torch.float16, torch.bfloat16)
EXPECTED = {"nan": NonFiniteError, "inf": NonFiniteError, "shape": ShapeError, "mixed": DTypeError}


@dataclass
class Arg:
    """One tensor argument: ``make(gen, batch, dtype)`` builds a valid value.

    ``trailing``: the trailing shape the function requires (``None``: the argument is elementwise, any
    shape — the shape mutation is skipped); an entry ``None`` is a free size (e.g. n of J (..., 6, n)),
    which the shape mutation leaves alone. ``batched``: its leading dims are the call's batch dims.
    ``finite``: NaN/inf must be refused (False where inf is meaningful, e.g. limits).
    """

    make: Callable[[torch.Generator, tuple[int, ...], torch.dtype], Tensor]
    trailing: tuple[int | None, ...] | None = None
    batched: bool = True
    finite: bool = True


@dataclass
class Case:
    """A public function and how to call it.

    ``args``: the tensor arguments by name, in positional order unless ``keyword`` lists them.
    ``fixed``: further keyword arguments (not fuzzed). ``out_batch``: maps the result to the tensor whose
    leading dims must equal the call's batch dims (default: the result itself, or the first tensor of a
    tuple/dataclass); ``None`` skips the batch-dims check (results without batch dims).
    ``chain``: None, or ``chain(dtype)`` giving the object (a chain) of the call's dtype, passed to ``fn`` as
    its first argument (before the tensor arguments); the ``mixed`` mutation then converts an argument away
    from the chain's dtype (``follows_chain`` is implied).
    """

    name: str
    fn: Callable
    args: dict[str, Arg]
    fixed: dict[str, Any] = field(default_factory=dict)
    keyword: Sequence[str] = ()
    out_batch: Callable[[Any], Tensor] | None | str = "default"
    skip: Sequence[str] = ()  # mutations that do not apply, each with a reason in the case list
    follows_chain: bool = False  # the call's dtype is a chain's: a lone tensor argument can still mix
    covers: Callable | None = None  # the public callable this case fuzzes, when ``fn`` is a wrapper
    #: the typed error an empty batch must raise where no result can exist (e.g. calibration from 0 poses)
    empty_raises: type[Exception] | None = None
    chain: Callable[[torch.dtype], Any] | None = None  # the chain of the call's dtype, fn's first argument

    @property
    def target(self) -> Callable:
        return self.covers if self.covers is not None else self.fn
    batch: tuple[int, ...] = (3,)
    rtol: float = 1e-6

    def call(self, values: dict[str, Any]):
        pos = [values[k] for k in self.args if k not in self.keyword]
        kw = {k: values[k] for k in self.keyword}
        if self.chain is not None:
            pos.insert(0, self.chain(call_dtype()))
        return self.fn(*pos, **kw, **self.fixed)


def mutations(case: Case) -> list[str]:
    out = ["valid", "empty", "numpy"]
    for name, a in case.args.items():
        if a.finite:
            out += [f"nan:{name}", f"inf:{name}"]
        if a.trailing and any(d is not None for d in a.trailing):
            out.append(f"shape:{name}")
        out += [f"dtype:{name}:{str(d).removeprefix('torch.')}" for d in BAD_DTYPES]
        if len(case.args) > 1 or case.follows_chain or case.chain is not None:
            out.append(f"mixed:{name}")
    return [m for m in out if m.split(":")[0] not in case.skip and m not in case.skip]


def _leaves(x) -> list[Tensor]:
    if isinstance(x, Tensor):
        return [x]
    if isinstance(x, dict):
        return [t for v in x.values() for t in _leaves(v)]
    if isinstance(x, list | tuple):
        return [t for v in x for t in _leaves(v)]
    if hasattr(x, "__dataclass_fields__"):
        return [t for k in x.__dataclass_fields__ for t in _leaves(getattr(x, k))]
    return []


def _first(x) -> Tensor | None:
    leaves = _leaves(x)
    return leaves[0] if leaves else None


def _batch_ok(case: Case, result, batch: tuple[int, ...]) -> bool:
    if case.out_batch is None:
        return True
    t = _first(result) if case.out_batch == "default" else case.out_batch(result)
    return t is not None and tuple(t.shape[: len(batch)]) == batch


def _finite(result) -> bool:
    return all(bool(torch.isfinite(t).all()) for t in _leaves(result) if t.is_floating_point())


def _build(case: Case, gen: torch.Generator, batch: tuple[int, ...], dtype: torch.dtype) -> dict[str, Tensor]:
    return {k: a.make(gen, batch if a.batched else (), dtype) for k, a in case.args.items()}


def _poke(t: Tensor, value: float, gen: torch.Generator) -> Tensor:
    t = t.detach().clone()
    flat = t.view(-1)
    flat[int(torch.randint(flat.numel(), (1,), generator=gen))] = value
    return t


def _reshape_bad(t: Tensor, trailing: tuple[int | None, ...], gen: torch.Generator) -> Tensor:
    """A tensor whose trailing shape differs from ``trailing``: its last fixed-size dim one larger, or one
    dim missing."""
    if bool(torch.randint(2, (1,), generator=gen)) and len(trailing) > 1 and t.ndim >= 2:
        dropped = t[..., 0, :]  # drops a trailing dim of a matrix argument
        k = len(trailing)
        still_fits = dropped.ndim >= k and all(
            d is None or s == d for s, d in zip(dropped.shape[dropped.ndim - k :], trailing)
        )
        if not still_fits:  # (3, 3, 3) -> (3, 3) is one valid matrix: pad instead
            return dropped
    dim = max(i for i, d in enumerate(trailing) if d is not None) - len(trailing)  # last fixed-size dim
    pad = torch.zeros(*t.shape[:dim], 1, *t.shape[dim + 1 :], dtype=t.dtype) if dim < -1 else \
        torch.zeros(*t.shape[:-1], 1, dtype=t.dtype)
    return torch.cat((t, pad), dim=dim)


#: the float dtype of the call :func:`outcome` is running (before its mutation): wrappers of functions that
#: take a chain build the chain in it (see :func:`call_dtype`)
_CALL_DTYPE: list[torch.dtype] = [torch.float64]


def call_dtype() -> torch.dtype:
    """The dtype of the call being fuzzed, for a case's ``fn`` that must build a chain (``follows_chain``)."""
    return _CALL_DTYPE[0]


class Timeout(Exception):
    pass


def _alarm(_signum, _frame):
    raise Timeout


def outcome(case: Case, mutation: str, seed: int = 0, dtype: torch.dtype = torch.float64,
            time_limit: float = 20.0) -> tuple[str, str]:
    """Run one mutated call; return (class, detail) with class in typed/correct/silent/crash/hang."""
    gen = torch.Generator().manual_seed(seed)
    kind, _, rest = mutation.partition(":")
    target, _, extra = rest.partition(":")
    batch = (0, *case.batch[1:]) if kind == "empty" else case.batch
    values: dict[str, Any] = _build(case, gen, batch, dtype)
    expected: type[Exception] | None = EXPECTED.get(kind)
    if kind == "empty" and case.empty_raises is not None:
        expected = case.empty_raises
    if kind == "nan":
        values[target] = _poke(values[target], math.nan, gen)
    elif kind == "inf":
        values[target] = _poke(values[target], math.inf * (1 if bool(torch.randint(2, (1,))) else -1), gen)
    elif kind == "shape":
        values[target] = _reshape_bad(values[target], case.args[target].trailing, gen)
    elif kind == "dtype":
        values[target] = values[target].to(getattr(torch, extra))
        expected = DTypeError
    elif kind == "mixed":
        other = torch.float32 if dtype == torch.float64 else torch.float64
        values[target] = values[target].to(other)
    elif kind == "numpy":
        reference_values = dict(values)
        values = {k: v.numpy() for k, v in values.items()}
    _CALL_DTYPE[0] = dtype
    old = signal.signal(signal.SIGALRM, _alarm)
    signal.setitimer(signal.ITIMER_REAL, time_limit)
    t0 = time.perf_counter()
    try:
        result = case.call(values)
    except Timeout:
        return "hang", f"over {time_limit:.0f} s"
    except DiffkinError as exc:
        if expected is not None and isinstance(exc, expected):
            return "typed", f"{type(exc).__name__}: {exc}"
        return ("silent" if expected is None else "crash"), f"{type(exc).__name__}: {exc}"
    except Exception as exc:  # noqa: BLE001 - classifying every failure is the point
        return "crash", f"{type(exc).__name__}: {exc}"
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)
    del t0
    if expected is not None:
        return "silent", f"no {expected.__name__} for {mutation}"
    if not _batch_ok(case, result, batch):
        got = _first(result)
        return "silent", f"batch dims {batch} expected, got {None if got is None else tuple(got.shape)}"
    if not _finite(result):
        return "silent", "NaN or inf in the result of finite input"
    if kind == "numpy":
        reference = case.call(reference_values)
        for a, b in zip(_leaves(result), _leaves(reference)):
            if a.dtype != b.dtype or not (torch.allclose(a, b, rtol=case.rtol, atol=case.rtol)
                                          if a.is_floating_point() else torch.equal(a, b)):
                return "silent", f"numpy input gave {a.dtype} values unequal to the tensor input's {b.dtype}"
    return "correct", ""


# ------------------------------------------------------------------------------------- value builders
def uniform(*trailing: int, low: float = -1.0, high: float = 1.0):
    """``make`` for uniform values in [low, high) of shape (*batch, *trailing)."""

    def make(gen, batch, dtype):
        return low + (high - low) * torch.rand((*batch, *trailing), generator=gen, dtype=dtype)

    return make


def rotation(gen, batch, dtype):
    """Random rotation matrices (..., 3, 3) from normalised quaternions."""
    q = torch.randn(*batch, 4, generator=gen, dtype=torch.float64)
    q = q / q.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    R = torch.stack(
        (
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ),
        dim=-1,
    ).reshape(*batch, 3, 3)
    return R.to(dtype)


def transform(gen, batch, dtype):
    """Random rigid transforms (..., 4, 4)."""
    T = torch.zeros(*batch, 4, 4, dtype=dtype)
    T[..., :3, :3] = rotation(gen, batch, dtype)
    T[..., :3, 3] = torch.rand(*batch, 3, generator=gen, dtype=dtype)
    T[..., 3, 3] = 1
    return T


def unit_quaternion(gen, batch, dtype):
    q = torch.randn(*batch, 4, generator=gen, dtype=torch.float64)
    return (q / q.norm(dim=-1, keepdim=True)).to(dtype)


def constant(value):
    """``make`` for a fixed tensor (not batched)."""

    def make(gen, batch, dtype):
        return torch.as_tensor(value, dtype=dtype).expand(*batch, *torch.as_tensor(value).shape).clone()

    return make


def main() -> None:
    """Print the sweep's counts over every case, 3 seeds, float32 and float64, and the failures."""
    from tests.fuzzing import mutations, outcome  # the imported module, not __main__: one call_dtype() state
    from tests.test_fuzz import CASES

    cases = list(CASES.values())
    counts: Counter = Counter()
    failures = []
    for case in cases:
        for m in mutations(case):
            for seed in (0, 1, 2):
                for dtype in (torch.float64, torch.float32):
                    kind, detail = outcome(case, m, seed, dtype)
                    counts[kind] += 1
                    if kind not in ("typed", "correct"):
                        failures.append(f"{kind:7s} {case.name} [{m}] {dtype}: {detail[:160]}")
    print("\n".join(failures))
    print(f"{len(cases)} functions; tried {sum(counts.values())}: "
          + ", ".join(f"{k} {counts[k]}" for k in ("typed", "correct", "silent", "crash", "hang")))


if __name__ == "__main__":
    main()

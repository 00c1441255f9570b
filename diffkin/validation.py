"""The shared validators of diffkin's public boundary: one rule for what a public function accepts.

Every public function that takes numbers runs its arguments through :func:`tensors` (or the single-argument
helpers below) once, on entry; the kernels behind it trust their input. The rule:

* **Tensors are taken as they are**: float32 or float64, one dtype and one device per call. Integer, bool,
  complex, float16 and bfloat16 tensors raise :class:`~diffkin.errors.DTypeError` (half precision cannot
  meet IK and calibration tolerances: convert with ``.float()``); tensors of two float dtypes or two devices
  in one call raise :class:`~diffkin.errors.DTypeError` naming both.
* **Everything else that holds numbers is converted**: Python numbers, (nested) sequences and numpy arrays of
  float or integer dtype become tensors of the call's dtype and device — the chain's for a chain or a
  function that takes one, else that of the call's tensor arguments, else float64 for a float64 numpy array
  and torch's default dtype otherwise. Bool, complex, float16 and object data are refused (``DTypeError``).
* **Shapes**: trailing dimensions must match exactly (:class:`~diffkin.errors.ShapeError` names the expected
  and received shape; nothing is broadcast into a wrong trailing shape); leading batch dimensions are free
  and may be empty (empty batches give empty results).
* **Values**: NaN or inf raise :class:`~diffkin.errors.NonFiniteError` (``finite=False`` skips it where inf is
  meaningful, e.g. joint limits). The check is one reduction on the device plus one host read, skipped while
  ``torch.compile`` traces or inside ``torch.func`` transforms, where it cannot read values.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from numbers import Number
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ._numerics import broadcast_shapes
from .errors import (
    DeviceError,
    DTypeError,
    ModelError,
    NonFiniteError,
    NonFiniteOptionError,
    OptionError,
    ShapeError,
)

__all__ = [
    "SUPPORTED_DTYPES",
    "as_tensor",
    "broadcast_batch",
    "check_broadcasts_to",
    "check_count",
    "check_device",
    "check_end_links",
    "check_fits_dtype",
    "check_given",
    "check_dtype",
    "check_lower_bound",
    "check_nonnegative",
    "check_number",
    "check_positive",
    "check_finite",
    "check_shape",
    "check_tensor",
    "check_trailing",
    "common_dtype_device",
    "shape_str",
    "tensors",
]

#: The floating dtypes every public function computes in.
SUPPORTED_DTYPES = (torch.float32, torch.float64)

Trailing = Sequence["int | None"] | None  # None: any shape; an entry None: any size on that axis


def shape_str(shape: Sequence[int]) -> str:
    """``(2, 3)``: a shape as users write it."""
    return "(" + ", ".join(str(s) for s in shape) + ")"


def _expected_str(trailing: Sequence[int | None]) -> str:
    dims = ["..."] + ["*" if t is None else str(t) for t in trailing]
    return "(" + ", ".join(dims) + ")"


def check_dtype(x: Tensor, name: str) -> Tensor:
    """Raise :class:`DTypeError` unless ``x`` is a float32 or float64 tensor."""
    if x.dtype in SUPPORTED_DTYPES:
        return x
    if x.dtype in (torch.float16, torch.bfloat16):
        raise DTypeError(
            f"{name} has dtype {x.dtype}, which diffkin does not support (half precision cannot meet its "
            f"tolerances); expected float32 or float64: convert with {name}.float()"
        )
    raise DTypeError(f"expected {name} as a float32 or float64 tensor, got dtype {x.dtype}")


def check_tensor(x: Any, name: str) -> Tensor:
    """Raise :class:`DTypeError` unless ``x`` is a float32 or float64 ``torch.Tensor`` (no conversion)."""
    if not isinstance(x, Tensor):
        raise DTypeError(f"expected {name} as a float32 or float64 torch.Tensor, got {type(x).__name__}")
    return check_dtype(x, name)


def check_trailing(x: Tensor, trailing: Sequence[int | None], name: str) -> Tensor:
    """Raise :class:`ShapeError` unless ``x``'s trailing dims are ``trailing`` (None: any size)."""
    k = len(trailing)
    ok = x.ndim >= k and all(t is None or s == t for s, t in zip(x.shape[x.ndim - k :], trailing))
    if not ok:
        raise ShapeError(f"expected {name} of shape {_expected_str(trailing)}, got {shape_str(x.shape)}")
    return x


def check_shape(x: Any, trailing: Sequence[int | None], name: str) -> Tensor:
    """:func:`check_tensor` and :func:`check_trailing` in one call."""
    return check_trailing(check_tensor(x, name), trailing, name)


def _traced(x: Tensor) -> bool:
    """Values cannot be read: torch.compile is tracing, or ``x`` is wrapped by a torch.func transform."""
    if torch.compiler.is_compiling():
        return True
    plain = type(x) in (Tensor, torch.nn.Parameter)
    return not plain or torch._C._functorch.is_functorch_wrapped_tensor(x)


def check_finite(x: Tensor, name: str) -> Tensor:
    """Raise :class:`NonFiniteError` if ``x`` holds NaN or inf (skipped while tracing; see module doc)."""
    if x.numel() == 0 or _traced(x):
        return x
    with torch.no_grad():
        # one cheap reduction: a finite sum means every entry is finite; an inf sum may be an overflow of
        # large finite values (float32 at 1e30), so the exact elementwise test decides then. The sum is
        # tested on the host: torch.isfinite of a 0-d tensor is four more operator calls.
        if math.isfinite(x.sum().item()) or bool(torch.isfinite(x).all()):
            return x
        bad = int((~torch.isfinite(x)).sum())
    raise NonFiniteError(f"{name} contains NaN or inf ({bad} of {x.numel()} values); expected finite numbers")


def _numpy_dtype(a: np.ndarray, name: str) -> torch.dtype | None:
    """The torch dtype a numpy array keeps when nothing else decides (None: torch's default), or refuse."""
    kind = a.dtype.kind
    if kind == "f" and a.dtype.itemsize >= 4:
        return torch.float64 if a.dtype == np.float64 else torch.float32
    if kind in "iu":
        return None
    what = {"b": "bool", "c": "complex", "f": "float16", "O": "object"}.get(kind, str(a.dtype))
    raise DTypeError(f"expected {name} as float or integer numbers, got a numpy array of {what} dtype")


def _numpy_common_dtype(arrays: list[tuple[str, Any]]) -> torch.dtype | None:
    kept = [_numpy_dtype(np.asarray(v), name) for name, v in arrays]
    if torch.float64 in kept:
        return torch.float64
    return torch.float32 if kept and None not in kept else None


def as_tensor(x: Any, name: str, *, dtype: torch.dtype | None = None, device=None) -> Tensor:
    """One argument by the module's rule: a tensor is checked (float32/float64) and returned as it is; a
    Python number, sequence or numpy array is converted to ``dtype``/``device`` (defaults: see module doc)."""
    if isinstance(x, Tensor):
        return check_dtype(x, name)
    if type(x) is float or type(x) is int:  # the common option value, without numpy (traceable by dynamo)
        return torch.tensor(x, dtype=dtype or torch.get_default_dtype(), device=device)
    if isinstance(x, bool | np.bool_):
        raise DTypeError(f"expected {name} as a number, got bool {x}")
    if isinstance(x, np.ndarray | np.generic):
        arr = np.asarray(x)
        keep = _numpy_dtype(arr, name)
        return torch.as_tensor(arr, device=device).to(dtype or keep or torch.get_default_dtype())
    if isinstance(x, Number | Sequence) and not isinstance(x, str | bytes):
        try:
            arr = np.asarray(x)
        except ValueError as exc:  # ragged nested sequences
            raise ShapeError(f"{name} is a ragged sequence ({exc})") from None
        if arr.dtype.kind not in "iuf":
            raise DTypeError(f"expected {name} as numbers, got {type(x).__name__} of {arr.dtype}")
        return torch.as_tensor(arr, device=device).to(dtype or torch.get_default_dtype())
    raise DTypeError(f"expected {name} as a float32/float64 torch.Tensor or numbers, got {type(x).__name__}")


def common_dtype_device(named: dict[str, Tensor]) -> tuple[torch.dtype | None, torch.device | None]:
    """The one dtype and device of the named tensors; :class:`DTypeError` naming both on a mix."""
    first: tuple[str, Tensor] | None = None
    for name, t in named.items():
        if first is None:
            first = (name, t)
            continue
        n0, t0 = first
        if t.dtype != t0.dtype:
            raise DTypeError(
                f"expected one dtype, got {n0}: {t0.dtype} and {name}: {t.dtype}; convert one of them"
            )
        if t.device != t0.device:
            raise DTypeError(f"expected one device, got {n0} on {t0.device} and {name} on {t.device}")
    return (None, None) if first is None else (first[1].dtype, first[1].device)


def tensors(
    *specs: tuple[str, Any, Trailing],
    like: Tensor | torch.nn.Module | None = None,
    finite: bool | Sequence[bool] = True,
) -> tuple[Tensor, ...]:
    """Validate a call's arguments together, by the module's rule.

    Args:
        specs: ``(name, value, trailing)`` per argument; ``trailing`` is the required trailing shape (entries
            None for any size) or None for any shape. ``None`` values pass through as None.
        like: a chain (anything with ``dtype`` and ``device``) or tensor whose dtype and device the call
            must use: tensors must match it, other inputs are converted to it.
        finite: check every argument (or per argument) for NaN/inf.

    Returns:
        the arguments as tensors, in order.
    """
    flags = [finite] * len(specs) if isinstance(finite, bool) else list(finite)
    given = {name: v for name, v, _ in specs if isinstance(v, Tensor)}
    for name, v in given.items():
        check_dtype(v, name)
    if like is not None:
        if like.dtype not in SUPPORTED_DTYPES:  # e.g. chain.half(): the chain itself left the rule
            raise DTypeError(f"the chain is {like.dtype}; diffkin computes in float32 or float64: convert it "
                             "with chain.float() or chain.double()")
        target = ("chain" if isinstance(like, torch.nn.Module) else "reference", like)
        probe = torch.empty(0, dtype=like.dtype, device=like.device)
        common_dtype_device({target[0]: probe, **given})
        dtype, device = like.dtype, like.device
    else:
        dtype, device = common_dtype_device(given)
        if dtype is None:  # no tensor decides: the numpy arguments' widest float dtype, else torch's default
            arrays = [(n, v) for n, v, _ in specs if isinstance(v, np.ndarray | np.generic)]
            dtype = _numpy_common_dtype(arrays)
    out = []
    for (name, v, trailing), check in zip(specs, flags):
        if v is None:
            out.append(None)
            continue
        t = as_tensor(v, name, dtype=dtype, device=device)
        if trailing is not None:
            check_trailing(t, trailing, name)
        if check:
            check_finite(t, name)
        out.append(t)
    return tuple(out)


def broadcast_batch(*specs: tuple[str, Tensor | None, int]) -> torch.Size:
    """The common batch shape of a call's arguments: ``(name, tensor, k)`` per argument, whose batch dims are
    all but its last ``k``; ``None`` tensors are skipped. :class:`ShapeError` names the shapes that do not
    broadcast (instead of torch's error from deep inside the computation)."""
    given = [(n, t, k) for n, t, k in specs if t is not None]
    try:
        return broadcast_shapes(*(t.shape[: t.ndim - k] for _, t, k in given))
    except RuntimeError:
        got = ", ".join(f"{n} {shape_str(t.shape)}" for n, t, _ in given)
        raise ShapeError(f"expected arguments whose batch dims broadcast, got {got}") from None


def check_lower_bound(x: Tensor, name: str, bound: float = 0.0, *, strict: bool = False,
                      cls: type[Exception] = OptionError, nan: bool = True) -> Tensor:
    """The one rule of the tensor option checks: raise ``cls`` (default
    :class:`~diffkin.errors.OptionError`) unless every entry of ``x`` is >= ``bound`` (``strict``: >
    ``bound``), naming how many are not and the smallest. NaN is left to :func:`check_finite` unless
    ``nan=False`` (options that may be inf and so are not checked finite): then a NaN raises
    :class:`~diffkin.errors.NonFiniteOptionError`. Skipped while tracing (the values cannot be read)."""
    if x.numel() == 0 or _traced(x):
        return x
    with torch.no_grad():
        op = ">" if strict else ">="
        if not nan and bool(torch.isnan(x).any()):
            raise NonFiniteOptionError(f"expected {name} {op} {bound:g}, got {int(torch.isnan(x).sum())} NaN "
                                       "value(s)")
        bad = x <= bound if strict else x < bound
        if bool(bad.any()):
            n = int(bad.sum())
            got = (f"{n} {'non-positive' if strict else 'negative'} value(s)" if bound == 0
                   else f"{n} value(s) {'<=' if strict else '<'} {bound:g}")
            raise cls(f"expected {name} {op} {bound:g}, got {got} (smallest {float(x.min()):.3g})")
    return x


def check_nonnegative(x: Tensor, name: str, *, nan: bool = True) -> Tensor:
    """Raise :class:`~diffkin.errors.OptionError` if ``x`` has an entry < 0 (a damping, a weight; NaN as
    :func:`check_lower_bound`): :func:`check_lower_bound` at 0."""
    return check_lower_bound(x, name, nan=nan)


def check_positive(x: Tensor, name: str, *, nan: bool = True) -> Tensor:
    """Raise :class:`~diffkin.errors.OptionError` if ``x`` has an entry <= 0 (a damping that makes a step
    unique, a time step; NaN as :func:`check_lower_bound`)."""
    return check_lower_bound(x, name, strict=True, nan=nan)


def check_number(x: Any, name: str, *, positive: bool = True, unit: str = "") -> float:
    """An option given as a finite Python number > 0 (``positive``) or >= 0, as float; else
    :class:`~diffkin.errors.OptionError` naming it (tolerances, dampings, scales): NaN and inf raise
    :class:`~diffkin.errors.NonFiniteOptionError`, which is an OptionError and a NonFiniteError."""
    ok = isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x) and (
        x > 0 if positive else x >= 0)
    if not ok:
        bound = "> 0" if positive else ">= 0"
        # NaN/inf keep the rule's error class (and are OptionErrors: one type for every option's mistake)
        cls = NonFiniteOptionError if isinstance(x, float) and not math.isfinite(x) else OptionError
        raise cls(f"expected {name} as a finite number {bound}{unit}, got {x!r}")
    return float(x)


def check_count(x: Any, name: str, minimum: int = 1, maximum: int | None = None) -> int:
    """An option given as a Python integer >= ``minimum`` (and <= ``maximum`` when given: seeds, iterations,
    sizes); else :class:`~diffkin.errors.OptionError` naming it."""
    if isinstance(x, bool) or not isinstance(x, int | np.integer) or x < minimum or \
            (maximum is not None and x > maximum):
        bound = f">= {minimum}" if maximum is None else f"in [{minimum}, {maximum}]"
        raise OptionError(f"expected {name} as an integer {bound}, got {x!r}")
    return int(x)


def check_device(device: Any, name: str = "device") -> torch.device | None:
    """``device`` (None, a string or a ``torch.device``) as a ``torch.device`` this torch can compute on;
    :class:`~diffkin.errors.DeviceError` for an unknown string, ``"meta"`` (tensors without values), CUDA
    on a build or machine without it, or a GPU index that does not exist. None passes through."""
    if device is None:
        return None
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError):
        raise DeviceError(f"expected {name} as 'cpu', 'cuda' or 'cuda:N', got {device!r}") from None
    if dev.type == "meta":
        raise DeviceError(f"{name} 'meta' holds no values; diffkin computes on 'cpu' or 'cuda'")
    if dev.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if count == 0:
            raise DeviceError(f"{name} {str(device)!r} was requested but this torch has no CUDA device "
                              f"(CUDA build: {torch.version.cuda or 'no'}); use 'cpu'")
        if dev.index is not None and dev.index >= count:
            raise DeviceError(f"{name} {str(device)!r}: there are {count} CUDA devices (0 to {count - 1})")
    elif dev.type != "cpu":
        backend = getattr(torch.backends, dev.type, None)
        if backend is None or not getattr(backend, "is_available", lambda: False)():
            raise DeviceError(f"{name} {str(device)!r} is not available in this torch; use 'cpu' or 'cuda'")
    return dev


def check_fits_dtype(x: Any, dtype: torch.dtype, name: str, cls: type[Exception] = ModelError) -> Any:
    """Refuse finite numbers in ``x`` (a tensor, numbers or an array) that ``dtype`` cannot hold: converted,
    they would silently become ±inf (1e39 in float32). ±inf and NaN are left to the caller's rule."""
    src = x.detach() if isinstance(x, Tensor) else as_tensor(x, name, dtype=torch.float64)
    if not src.is_floating_point() or torch.finfo(src.dtype).max <= torch.finfo(dtype).max:
        return x
    big = torch.isfinite(src) & (src.abs() > torch.finfo(dtype).max)
    if bool(big.any()):
        worst = float(src[big].abs().max())
        raise cls(f"{name} holds {int(big.sum())} finite values beyond the range of {dtype} (|x| <= "
                  f"{torch.finfo(dtype).max:.4g}), e.g. {worst:.4g}, which would become inf; expected values "
                  "that fit (±inf: no limit)")
    return x


def check_broadcasts_to(x: Tensor | None, shape: Sequence[int], name: str, of: str = "J") -> Tensor | None:
    """Raise :class:`ShapeError` unless ``x``'s shape broadcasts to ``shape`` (the batch dims of ``of``)
    without enlarging it: a per-batch option (a damping, a weight) of the wrong shape. None passes."""
    if x is None:
        return x
    try:
        ok = tuple(broadcast_shapes(x.shape, tuple(shape))) == tuple(shape)
    except RuntimeError:
        ok = False
    if not ok:
        raise ShapeError(f"expected {name} as a number or of a shape that broadcasts to the batch dims "
                         f"{shape_str(shape)} of {of}, got {shape_str(x.shape)}")
    return x


def check_given(x: Any, name: str, expected: str) -> Any:
    """``x`` unless it is None: :func:`tensors` passes None through (optional arguments), so a required one
    is checked first; :class:`DTypeError` ``expected {name} as {expected}, got None``."""
    if x is None:
        raise DTypeError(f"expected {name} as {expected}, got None")
    return x


def check_end_links(end_links, what: str = "link") -> tuple[bool, list[str]]:
    """``(single, names)`` of a model loader's ``end_link`` argument: one name (a chain with one end link,
    poses ``(..., 4, 4)``) or a non-empty list of distinct names (K end links, ``(..., K, 4, 4)``); anything
    else is a :class:`~diffkin.errors.ModelError` saying what was expected and what came."""
    single = isinstance(end_links, str)
    if not single and not isinstance(end_links, list | tuple):
        raise ModelError(f"end_link: expected a {what} name or a list of them, got "
                         f"{type(end_links).__name__}")
    ends = [end_links] if single else list(end_links)
    if not ends:
        raise ModelError(f"end_link: give a {what} name or a non-empty list of {what} names")
    bad = [e for e in ends if not isinstance(e, str)]
    if bad:
        raise ModelError(f"end_link: expected {what} names (str), got {bad[0]!r} ({type(bad[0]).__name__})")
    if len(set(ends)) != len(ends):
        raise ModelError(f"end_link: duplicate names in {ends}")
    return single, ends

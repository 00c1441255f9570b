"""Numerical helpers shared by the kernels: dtype-aware eps, checks, safe functions.

The "double where" pattern: where a formula is singular at some input (e.g. sin(x)/x at 0), first replace
the input by a harmless value on the singular branch, *then* evaluate, *then* select. A single
``torch.where`` would still back-propagate NaN from the unused branch.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = [
    "eps_for",
    "tol_for",
    "safe_norm",
    "safe_normalize",
    "normalize_floor",
    "stable_norm",
    "stable_normalize",
    "sinc",
    "safe_acos",
    "safe_atan2",
    "safe_sqrt",
    "cross",
    "wrap_angle",
    "broadcast_shapes",
]


def broadcast_shapes(*shapes) -> torch.Size:
    """``torch.broadcast_shapes`` of plain shapes (tuples or ``torch.Size``) without its dispatch: about 5 µs
    a call against 60 (a plan one at a time made some 20 of them). The same result, and a RuntimeError
    naming both sizes where they do not broadcast; traced calls (``torch.compile``) and symbolic sizes go to
    torch's."""
    if torch.compiler.is_compiling():
        return torch.broadcast_shapes(*shapes)
    n = max(map(len, shapes), default=0)
    out = [1] * n
    for shape in shapes:
        for i, d in enumerate(shape, n - len(shape)):
            if type(d) is not int:
                return torch.broadcast_shapes(*shapes)
            if d != 1:
                if out[i] == 1:
                    out[i] = d
                elif out[i] != d:
                    raise RuntimeError(f"shape mismatch: sizes {out[i]} and {d} do not broadcast at dim {i}")
    return torch.Size(out)


def eps_for(x: Tensor | torch.dtype) -> float:
    """Machine epsilon of ``x``'s dtype (float32: 1.19e-7, float64: 2.22e-16)."""
    dtype = x if isinstance(x, torch.dtype) else x.dtype
    return torch.finfo(dtype).eps


def tol_for(x: Tensor | torch.dtype, float64: float, float32: float) -> float:
    """The tolerance of ``x``'s dtype: ``float64`` for double precision, ``float32`` for every other
    floating dtype (single and lower). The one place a tolerance branches on the dtype: a call site states
    both values, so what float32 gets is written next to what float64 gets."""
    dtype = x if isinstance(x, torch.dtype) else x.dtype
    return float64 if dtype == torch.float64 else float32


def safe_sqrt(x: Tensor, eps: float | None = None) -> Tensor:
    """sqrt with a finite gradient at 0 (gradient 0 there instead of inf); 0 for x <= eps², NaN for NaN
    (NaN in, NaN out: a NaN coordinate never becomes a plausible zero length or distance)."""
    tiny = (eps if eps is not None else eps_for(x)) ** 2
    small = x <= tiny  # False for NaN: the NaN reaches the sqrt and the result
    return torch.where(small, torch.zeros_like(x), torch.sqrt(torch.where(small, torch.ones_like(x), x)))


def safe_norm(v: Tensor, dim: int = -1, keepdim: bool = False) -> Tensor:
    """Euclidean norm with a finite (zero) gradient at the zero vector; NaN where ``v`` holds NaN."""
    return safe_sqrt((v * v).sum(dim=dim, keepdim=keepdim))


def stable_norm(v: Tensor, dim: int = -1, keepdim: bool = False) -> Tensor:
    """:func:`safe_norm` without overflow or underflow of the squares (1e30 m in float32 gives 1e30, not
    inf): the vector is scaled by its largest |component| first (held constant for the gradient)."""
    m = v.detach().abs().amax(dim=dim, keepdim=True) if v.numel() else v.new_ones(())
    m = torch.where((m > 0) & torch.isfinite(m), m, torch.ones_like(m))
    n = safe_norm(v / m, dim=dim, keepdim=True) * m
    return n if keepdim else n.squeeze(dim)


def stable_normalize(v: Tensor, dim: int = -1, fallback: Tensor | None = None) -> Tensor:
    """:func:`safe_normalize` with the overflow-safe :func:`stable_norm`."""
    return _normalized(v, stable_norm(v, dim=dim, keepdim=True), dim, fallback)


def safe_normalize(v: Tensor, dim: int = -1, fallback: Tensor | None = None) -> Tensor:
    """``v / |v|``; where ``|v|`` is ~0 returns ``fallback`` (default: the first unit vector)."""
    return _normalized(v, safe_norm(v, dim=dim, keepdim=True), dim, fallback)


def normalize_floor(x: Tensor | torch.dtype) -> float:
    """The norm at or below which :func:`safe_normalize` gives its fallback (no direction): sqrt(eps) / 1000
    (float64: 1.5e-11, float32: 3.5e-7)."""
    return eps_for(x) ** 0.5 * 1e-3


def _normalized(v: Tensor, n: Tensor, dim: int, fallback: Tensor | None) -> Tensor:
    """``v / n`` with ``fallback`` where the norm ``n`` (keepdim) is ~0."""
    small = n <= normalize_floor(v)
    if fallback is None:
        fallback = torch.zeros_like(v)
        fallback.select(dim, 0).fill_(1.0)
    return torch.where(small, fallback, v / torch.where(small, torch.ones_like(n), n))


def sinc(x: Tensor) -> Tensor:
    """sin(x)/x with the Taylor series near 0 (exact value and gradient at 0)."""
    small = x.abs() < eps_for(x) ** 0.25
    x_safe = torch.where(small, torch.ones_like(x), x)
    x2 = x * x
    return torch.where(small, 1.0 - x2 / 6.0 + x2 * x2 / 120.0, torch.sin(x_safe) / x_safe)


def safe_acos(x: Tensor) -> Tensor:
    """acos clamped to [-1, 1] with finite gradients at the ends (gradient clipped, not inf)."""
    lim = 1.0 - eps_for(x)
    return torch.acos(x.clamp(-lim, lim))


def safe_atan2(y: Tensor, x: Tensor) -> Tensor:
    """atan2 with a zero (not NaN) gradient at y = x = 0."""
    zero = (y == 0) & (x == 0)
    x_safe = torch.where(zero, torch.ones_like(x), x)
    return torch.where(zero, torch.zeros_like(y), torch.atan2(y, x_safe))


def cross(a: Tensor, b: Tensor, dim: int = -1) -> Tensor:
    """a × b along ``dim`` (size 3), by components: cheaper than ``torch.linalg.cross`` on small tensors."""
    ax, ay, az = a.unbind(dim)
    bx, by, bz = b.unbind(dim)
    return torch.stack((ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx), dim)


def wrap_angle(x: Tensor) -> Tensor:
    """Angles mapped to (-π, π] by atan2(sin x, cos x) (smooth, finite gradient everywhere)."""
    return torch.atan2(torch.sin(x), torch.cos(x))

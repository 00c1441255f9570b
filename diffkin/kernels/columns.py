"""Frames as columns: the arithmetic of the chain product (2.50) without 4×4 matmuls.

A frame F = [[x y z p], [0 0 0 1]] is kept as its four columns ``(x, y, z, p)``. Two layouts use the same
functions, because every operation below is elementwise on the columns:

* **batch last** (``dim=0``): each column is ``(3, B)`` (or ``(3, 1)`` for a constant frame): one contiguous
  vectorised pass per operation, the fast layout for large CPU batches;
* **batch first** (``dim=-1``): each column is ``(..., 3)``; coefficients broadcast as ``(..., 1)``.

Right-multiplying F by a fixed rigid transform T gives column j of F·T = Σ_k T[k, j] col_k (with p picking up
T[3, 3] = 1). A fixed transform is given either as a tensor ``(4, 4)`` (differentiable; in the batch-first
layout also ``(..., 4, 4)`` per sample or per joint) or as a :data:`Plan` of Python floats, whose zero terms
are skipped and ±1 terms need no multiply: real robots' fixed rotations are mostly signed permutations, so
a constant DH step costs a handful of fused multiply-adds. A joint moves about the z axis of its frame:
F · Rz(q) rotates the pair (x, y); F · Tz(q) moves p along z.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = [
    "Columns",
    "Plan",
    "Fixed",
    "plan_of",
    "axpy",
    "rotate",
    "apply_fixed",
    "apply_motion",
    "rotate_columns",
    "identity_columns",
    "transform_columns",
    "columns_to_matrices",
    "stack_columns",
]

Columns = tuple[Tensor, Tensor, Tensor, Tensor]  # x, y, z, p of one frame
Plan = tuple[tuple[tuple[float, float, float], ...], tuple[float, float, float]]  # (R 3×3, t 3) as floats
Fixed = Tensor | Plan | None  # None: identity


def plan_of(T: Tensor, eps: float | None = None) -> Plan | None:
    """The Python-float plan of one fixed transform ``(4, 4)`` (evaluate it in float64 for exact values);
    entries within ``eps`` (default: one ulp of T's dtype) of 0 or ±1 are snapped to them (cos(π/2) = 6e-17
    becomes 0). None: the identity."""
    eps = torch.finfo(T.dtype).eps if eps is None else eps
    M = T.detach().cpu().tolist()
    snap = [[0.0 if abs(v) <= eps else (1.0 if abs(v - 1) <= eps else (-1.0 if abs(v + 1) <= eps else v))
             for v in row] for row in M]
    R = tuple(tuple(row[:3]) for row in snap[:3])
    t = tuple(row[3] for row in snap[:3])
    if R == ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)) and t == (0.0, 0.0, 0.0):
        return None
    return R, t


def axpy(p: Tensor, a, x: Tensor) -> Tensor:
    """p + a x for a tensor or Python-float ``a`` (skipped when a == 0.0)."""
    if isinstance(a, Tensor):
        return torch.addcmul(p, a, x)
    return p if a == 0.0 else torch.add(p, x, alpha=a)


def rotate(u: Tensor, v: Tensor, c, s) -> tuple[Tensor, Tensor]:
    """(c u + s v, c v − s u): the column pair of F · R(angle) with cos c and sin s (tensors or floats)."""
    if isinstance(c, Tensor):
        return torch.addcmul(c * u, s, v), torch.addcmul(c * v, s, u, value=-1.0)
    if s == 0.0:
        return (u, v) if c == 1.0 else (-u, -v)
    if c == 0.0:
        return (v, -u) if s == 1.0 else (-v, u)
    return torch.add(u * c, v, alpha=s), torch.add(v * c, u, alpha=-s)


def _combo(terms: list[tuple[float, Tensor]], zero: Tensor) -> Tensor:
    """Σ coef · tensor over the nonzero float terms (±1 without a multiply)."""
    if not terms:
        return torch.zeros_like(zero)
    (c0, v0), rest = terms[0], terms[1:]
    acc = v0 if c0 == 1.0 else -v0 if c0 == -1.0 else v0 * c0
    for c, v in rest:
        acc = torch.add(acc, v, alpha=c)
    return acc


def apply_fixed(frame: Columns, T: Fixed, dim: int = 0) -> Columns:
    """Columns of F · T for a fixed transform ``T`` (None, a :data:`Plan` or a tensor); ``dim`` is the
    component axis of the columns (0: batch last, -1: batch first)."""
    if T is None:
        return frame
    cols = frame[:3]
    if isinstance(T, tuple):  # constants: skip zero terms
        R, t = T
        new = [_combo([(R[k][j], cols[k]) for k in range(3) if R[k][j] != 0.0], cols[j]) for j in range(3)]
        terms = [(t[k], cols[k]) for k in range(3) if t[k] != 0.0]
        p = _combo([(1.0, frame[3]), *terms], frame[3]) if terms else frame[3]
        return new[0], new[1], new[2], p
    if dim == 0 and T.ndim == 2:  # batch last: one (4, 4) @ (4, 3B) product
        F = torch.stack(torch.broadcast_tensors(*frame))
        G = (T.transpose(0, 1) @ F.reshape(4, -1)).reshape(F.shape)
        return G[0], G[1], G[2], G[3]
    # batch first: coefficients T[..., k, j] broadcast over the component axis
    E = T[..., :3, :].unsqueeze(-1)  # (..., 3, 4, 1)
    x, y, z, p = frame
    new = [x * E[..., 0, j, :] + y * E[..., 1, j, :] + z * E[..., 2, j, :] for j in range(4)]
    return new[0], new[1], new[2], p + new[3]


def apply_motion(frame: Columns, q: Tensor, revolute) -> Columns:
    """Columns of F · Rz(q) (revolute) or F · Tz(q) (prismatic); ``q`` broadcasts against one component.

    ``revolute`` is a bool, or a bool tensor broadcasting like ``q`` for joints of both kinds at once.
    """
    x, y, z, p = frame
    if isinstance(revolute, Tensor):
        c = torch.where(revolute, torch.cos(q), torch.ones_like(q))
        s = torch.where(revolute, torch.sin(q), torch.zeros_like(q))
        x, y = rotate(x, y, c, s)
        return x, y, z, torch.addcmul(p, torch.where(revolute, torch.zeros_like(q), q), z)
    if revolute:
        x, y = rotate(x, y, torch.cos(q), torch.sin(q))
    else:
        p = torch.addcmul(p, q, z)
    return x, y, z, p


def rotate_columns(frame: Columns, R: Tensor, dim: int = 0) -> Columns:
    """Columns of F · [[R, 0], [0, 1]] for a per-sample rotation: column j is Σ_k R[k, j] col_k.

    ``R`` is ``(3, 3, B)`` in the batch-last layout (``dim=0``, columns ``(3, B)``), ``(..., 3, 3)`` in the
    batch-first one (columns ``(..., 3)``); p is unchanged."""
    x, y, z, p = frame
    if dim == 0:
        new = [x * R[0, j] + y * R[1, j] + z * R[2, j] for j in range(3)]
    else:
        E = R.unsqueeze(-1)  # (..., 3, 3, 1): coefficients broadcast over the component axis
        new = [x * E[..., 0, j, :] + y * E[..., 1, j, :] + z * E[..., 2, j, :] for j in range(3)]
    return new[0], new[1], new[2], p


def transform_columns(T: Tensor, dim: int = 0) -> Columns:
    """The columns of a transform ``(4, 4)`` (batch last: ``(3, 1)`` each) or ``(..., 4, 4)`` (batch first:
    ``(..., 3)`` each)."""
    if dim == 0:
        x, y, z, p = T[:3].unsqueeze(-1).unbind(1)
        return x, y, z, p
    x, y, z, p = T[..., :3, :].unbind(-1)
    return x, y, z, p


_IDENTITY: dict = {}


def identity_columns(like: Tensor, dim: int = 0) -> Columns:
    """The identity frame's columns in ``like``'s dtype/device (batch last ``(3, 1)``, batch first
    ``(3,)``)."""
    key = (like.dtype, like.device, dim)
    cols = _IDENTITY.get(key)
    if cols is None:  # constants, made once per dtype/device: a small-batch call spends no ops on them
        eye = torch.eye(3, dtype=like.dtype, device=like.device)
        if dim == 0:
            cols = eye[:, 0:1], eye[:, 1:2], eye[:, 2:3], torch.zeros_like(eye[:, 0:1])
        else:
            cols = eye[0], eye[1], eye[2], torch.zeros_like(eye[0])
        _IDENTITY[key] = cols
    return cols


def columns_to_matrices(frame: Columns, out: Tensor) -> Tensor:
    """Write batch-last columns ``(3, B)`` into ``out (B, 4, 4)``, whose last row already holds
    [0, 0, 0, 1]. Returns ``out``."""
    for j, col in enumerate(frame):
        out[..., :3, j] = col.T
    return out


def stack_columns(frame: Columns, dim: int = 0) -> Tensor:
    """Homogeneous matrices from columns, without in-place writes (autograd / ``torch.compile``):
    batch last ``(3, B)`` -> ``(B, 4, 4)``; batch first ``(..., 3)`` -> ``(..., 4, 4)``."""
    cols = torch.broadcast_tensors(*frame)
    top = torch.stack(cols, dim=-1) if dim != 0 else torch.stack(cols, dim=-1).permute(1, 0, 2)
    bottom = torch.zeros_like(top[..., :1, :])
    bottom[..., 0, 3] = 1.0
    return torch.cat((top, bottom), dim=-2)

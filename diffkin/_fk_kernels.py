"""Forward-kinematics kernels behind :mod:`diffkin.chain` (pure functions; the classes check and store).

Frames are kept as four columns ``x, y, z, p`` (rotation columns and origin) of shape ``(3, B)``: batch last,
so every update is one contiguous vectorised pass, and a DH step is a handful of fused multiply-adds instead
of a 4×4 matmul (which spends 7/16 of its flops on the constant last row and is slow for tiny matrices).
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence

import torch
from torch import Tensor

__all__ = ["Columns", "columns_to_matrices", "axpy", "rotate", "dh_frames", "dh_ee_components"]

Columns = tuple[Tensor, Tensor, Tensor, Tensor]  # x, y, z, p of one frame, each (3, B) or (3, 1)


def columns_to_matrices(frame: Columns, T: Tensor | None, out: Tensor) -> Tensor:
    """Write a column frame (optionally times the fixed transform ``T``) into ``out (B, 4, 4)``.

    ``out``'s last row must already hold [0, 0, 0, 1]. Returns the origin column written, batch last:
    ``(3, B)`` (or ``(3, 1)`` if it does not depend on the batch), equal to ``out[:, :3, 3].T``.
    """
    if T is None:
        for j, col in enumerate(frame):
            out[..., :3, j] = col.T
        return frame[3]
    F = torch.stack(torch.broadcast_tensors(*frame))  # (4, 3, B): columns x, y, z, p
    # F · T: new column j = sum_k T[k, j] col_k (p is the column with T[3, 3] = 1)
    F = (T.transpose(0, 1) @ F.reshape(4, -1)).reshape(F.shape)
    out[..., :3, :] = F.permute(2, 1, 0)
    return F[3]


def axpy(p: Tensor, a, x: Tensor) -> Tensor:
    """p + a x for a tensor or Python-float ``a`` (skipped when a == 0.0)."""
    if isinstance(a, Tensor):
        return torch.addcmul(p, a, x)
    return p if a == 0.0 else torch.add(p, x, alpha=a)


def rotate(u: Tensor, v: Tensor, c, s) -> tuple[Tensor, Tensor]:
    """(c u + s v, c v − s u): the columns pair of F · R(angle) with cos c and sin s (tensors or floats)."""
    if isinstance(c, Tensor):
        return torch.addcmul(c * u, s, v), torch.addcmul(c * v, s, u, value=-1.0)
    if s == 0.0:
        return (u, v) if c == 1.0 else (-u, -v)
    if c == 0.0:
        return (v, -u) if s == 1.0 else (-v, u)
    return torch.add(u * c, v, alpha=s), torch.add(v * c, u, alpha=-s)


def dh_frames(qs: Sequence[Tensor], plan, joint_types: str, standard: bool, frame: Columns
               ) -> Iterator[Columns]:
    """Column kernel of a DH chain: yields frames 0..n from the base ``frame``.

    ``plan`` holds ``(a, cos α, sin α, d, theta)`` per joint, as tensors (differentiable) or Python floats
    (constants: zero terms skipped, α = 0, ±π/2, π become swaps); ``qs`` the joint values, each ``(B,)``.
    """
    yield frame
    for q, jt, (a, ca, sa, d, theta) in zip(qs, joint_types, plan):
        if jt == "R":
            phi = q + theta if isinstance(theta, Tensor) or theta != 0.0 else q
            c, s = torch.cos(phi), torch.sin(phi)
        else:
            c, s = (torch.cos(theta), torch.sin(theta)) if isinstance(theta, Tensor) else \
                (math.cos(theta), math.sin(theta))
            d = q + d if isinstance(d, Tensor) or d != 0.0 else q
        frame = dh_step(frame, c, s, a, ca, sa, d, standard)
        yield frame


def dh_step(frame: Columns, c, s, a, ca, sa, d, standard: bool) -> Columns:
    """One DH link on the columns ``(x, y, z, p)`` of frame i-1 -> frame i; cos/sin of ϑ and α, a and d as
    tensors broadcasting against the columns (any layout) or Python floats."""
    x, y, z, p = frame
    if standard:  # Rz(ϑ) Tz(d) Tx(a) Rx(α)  (2.52)
        p = axpy(p, d, z)
        x, y = rotate(x, y, c, s)
        p = axpy(p, a, x)
        y, z = rotate(y, z, ca, sa)
    else:  # Rx(α_{i-1}) Tx(a_{i-1}) Rz(ϑ_i) Tz(d_i)
        p = axpy(p, a, x)
        y, z = rotate(y, z, ca, sa)
        x, y = rotate(x, y, c, s)
        p = axpy(p, d, z)
    return x, y, z, p


def dh_ee_components(qT: Tensor, a: Tensor, alpha: Tensor, d: Tensor, theta: Tensor, base: Tensor | None,
                      tool: Tensor | None, joint_types: str, standard: bool) -> Tensor:
    """End-effector poses ``(B, 4, 4)`` of a DH chain from ``qT (n, B)``, every frame entry its own ``(B,)``
    tensor: slower than the column kernel in eager mode (3× the ops) but the layout ``torch.compile`` fuses
    into one loop over the batch; used by :meth:`DHChain.compile`.
    """
    qs = qT.unbind(0)
    ca, sa = torch.cos(alpha), torch.sin(alpha)
    B0 = base if base is not None else torch.eye(4, dtype=qT.dtype, device=qT.device)
    x, y, z, p = ([B0[r, j] for r in range(3)] for j in range(4))

    def rot(u, v, c, s):
        return [ui * c + vi * s for ui, vi in zip(u, v)], [vi * c - ui * s for ui, vi in zip(u, v)]

    def axpy(u, k, v):
        return [ui + k * vi for ui, vi in zip(u, v)]

    for i, jt in enumerate(joint_types):
        if jt == "R":
            c, s, di = torch.cos(qs[i] + theta[i]), torch.sin(qs[i] + theta[i]), d[i]
        else:
            c, s, di = torch.cos(theta[i]), torch.sin(theta[i]), d[i] + qs[i]
        if standard:
            p = axpy(p, di, z)
            x, y = rot(x, y, c, s)
            p = axpy(p, a[i], x)
            y, z = rot(y, z, ca[i], sa[i])
        else:
            p = axpy(p, a[i], x)
            y, z = rot(y, z, ca[i], sa[i])
            x, y = rot(x, y, c, s)
            p = axpy(p, di, z)
    cols = [x, y, z, p]
    if tool is not None:
        cols = [[sum(cols[k][r] * tool[k, j] for k in range(4)) for r in range(3)] for j in range(3)] + \
            [[p[r] + sum(cols[k][r] * tool[k, 3] for k in range(3)) for r in range(3)]]
    zero, one = torch.zeros_like(qs[0]), torch.ones_like(qs[0])
    entries = [cols[j][r] for r in range(3) for j in range(4)] + [zero, zero, zero, one]
    # component-major stack (contiguous stores), then one transposing copy
    out = torch.stack(torch.broadcast_tensors(*entries), dim=0).transpose(0, 1).contiguous()
    return out.unflatten(1, (4, 4))

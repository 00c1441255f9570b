"""Closed-form IK of the industrial 6R families, recognised from the geometry of any chain (DH or URDF).

Two families, 8 branches each:

- ``ur`` — the Universal Robots geometry (UR3/5/10/16, e-series; Hawkins 2013): axes 2, 3, 4 parallel,
  1 ⟂ 2, 4 ⟂ 5, 5 ⟂ 6, axis 5 meeting axes 4 and 6 (the wrist is not spherical: the d5, d6 offsets);
- ``opw`` — ortho-parallel basis with a spherical wrist (Brandstötter, Angerer, Hofbaur 2014: ABB IRB, KUKA
  KR, Fanuc, Stäubli, Motoman, and the Puma 560 with its a3 / d3 offsets): 1 ⟂ 2, 2 ∥ 3, axes 4, 5, 6
  through one point (the wrist centre), 4 ⟂ 5; shoulder offset a1, elbow offset a2 and lateral offset b
  are all allowed.

Recognition and solution use only the joint lines at q = 0 (unit axis u_i and a point p_i of each axis,
:meth:`~diffkin.chain.KinematicChain.joint_axes_origins`, base folded in) and the end pose M = T(0) (tool
folded in). The chain is then the product of exponentials T(q) = e^{ξ_1 q_1} ··· e^{ξ_6 q_6} M, so the
solution comes back in the chain's own joint zeros and directions with no DH table at all: a URDF works as
a DH model does, joint signs and offsets included. Each step is a Paden–Kahan subproblem on these lines:

UR: the point w where axes 5 and 6 meet keeps its component along the parallel axes, n(q_1)·(w − p_1) = h
(shoulder ±); the angle between axis 6 and n(q_1) gives q_5 (wrist ±); q_6 rotates R^T n onto R_5^T u_2; the
point where axes 4 and 5 meet is then a planar 2R problem for q_2, q_3 (elbow ±), and q_4 takes the rest of
the rotation about the parallel axes.
OPW: the wrist centre w gives q_1 the same way (shoulder ±), then the planar 2R problem q_2, q_3 (elbow ±);
the wrist rotation R_4 R_5 R_6 = (R_1 R_2 R_3)^T R M^{-1} is solved by subproblem 2 (q_4, q_5; wrist ±)
and subproblem 1 (q_6).

Branch order (k = 8): UR shoulder major, then wrist, then elbow; OPW shoulder, elbow, wrist (first = the
+ root of each). Singular targets, where a subproblem has a continuum of solutions, get one representative
with finite values and zero (finite) gradients for the free angle: wrist singularity (UR q_5 = 0, π with
axis 6 parallel to axes 2–4: q_6 = 0; OPW axes 4 and 6 aligned: q_4 = 0, q_6 takes the whole rotation),
shoulder singularity (OPW wrist centre on axis 1: q_1 = ±π/2 from the base's zero direction), elbow
stretched or folded (the two elbow branches coincide). The arguments of the inverse cosines are written as
atan2(√(r² − k²), k) with a √ that has a zero gradient at 0, so values and gradients stay finite also at
the workspace boundary; unreachable targets come back finite and flagged invalid.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .._numerics import cross, eps_for
from ..errors import ModelError
from ..kernels import cache
from ..rotations import _axis_angle_to_matrix
from ..transforms import _transform_inverse

__all__ = ["INDUSTRIAL_FAMILIES", "recognise_industrial", "industrial_parameters", "solve_industrial"]

INDUSTRIAL_FAMILIES = ("ur", "opw")
_ANGLE_TOL = 1e-6  # |cos| / |sin| of the angle between axes
_LENGTH_TOL = 1e-6  # [m], relative to 1 + the arm's size


# ------------------------------------------------------------------------------------- geometry
def _zero_lines(chain) -> tuple[Tensor, Tensor, Tensor]:
    """Unit axes u (6, 3), points p (6, 3) at q = 0 and M = T(0) (4, 4), base and tool folded in;
    differentiable w.r.t. the chain's parameters."""
    q0 = torch.zeros(chain.n_joints, dtype=chain.dtype, device=chain.device)
    u, p, _ = chain.joint_axes_origins(q0)
    u = u / u.norm(dim=-1, keepdim=True)
    return u, p, chain.forward_kinematics(q0)


def _closest(pa: Tensor, ua: Tensor, pb: Tensor, ub: Tensor) -> tuple[Tensor, Tensor]:
    """Closest points of two non-parallel lines (point, unit direction): (on a, on b)."""
    w = pa - pb
    b, d, e = ua @ ub, ua @ w, ub @ w
    den = 1.0 - b * b
    s, t = (b * e - d) / den, (e - b * d) / den
    return pa + s * ua, pb + t * ub


def _perp(v: Tensor, u: Tensor) -> Tensor:
    """Component of v (..., 3) orthogonal to the unit vector u (3,)."""
    return v - (v @ u)[..., None] * u


def _checks(u, p, scale: float) -> tuple[dict[str, list[tuple[str, bool]]], dict]:
    """Every family's conditions as (description, passed), on float64 CPU copies; and the points needed."""
    u = u.detach().double().cpu()
    p = p.detach().double().cpu()
    ltol = _LENGTH_TOL * scale

    def par(i, j):
        return float(torch.linalg.cross(u[i], u[j]).norm()) <= _ANGLE_TOL

    def perp(i, j):
        return abs(float(u[i] @ u[j])) <= _ANGLE_TOL

    def meet(i, j):
        if par(i, j):
            return float(_perp(p[j] - p[i], u[i]).norm()) <= ltol
        a, b = _closest(p[i], u[i], p[j], u[j])
        return float((a - b).norm()) <= ltol

    def dist(i, j):  # distance between two parallel axes
        return float(_perp(p[j] - p[i], u[i]).norm())

    ur = [("axis 1 ⟂ axis 2", perp(0, 1)), ("axes 2 ∥ 3", par(1, 2)), ("axes 3 ∥ 4", par(2, 3)),
          ("axis 4 ⟂ axis 5", perp(3, 4)), ("axis 5 ⟂ axis 6", perp(4, 5)),
          ("axes 4 and 5 meet", not par(3, 4) and meet(3, 4)),
          ("axes 5 and 6 meet", not par(4, 5) and meet(4, 5))]  # fmt: skip
    if all(ok for _, ok in ur):
        x45 = _closest(p[3], u[3], p[4], u[4])[0]
        ur += [("axes 2, 3 apart", dist(1, 2) > ltol), ("axis 3 and the 4–5 point apart",
               float(_perp(x45 - p[2], u[1]).norm()) > ltol)]  # fmt: skip
    opw = [("axis 1 ⟂ axis 2", perp(0, 1)), ("axes 2 ∥ 3", par(1, 2)), ("axis 4 ⟂ axis 5", perp(3, 4)),
           ("axes 4 and 5 meet", not par(3, 4) and meet(3, 4))]  # fmt: skip
    if all(ok for _, ok in opw):
        c = _closest(p[3], u[3], p[4], u[4])[0]
        on6 = float(_perp(c - p[5], u[5]).norm()) <= ltol
        opw += [("axis 6 through the 4–5 point (spherical wrist)", on6),
                ("axis 6 ∦ axis 5", not par(4, 5)), ("axes 2, 3 apart", dist(1, 2) > ltol),
                ("axis 3 and the wrist centre apart",
                 float(_perp(c - p[2], u[1]).norm()) > ltol)]  # fmt: skip
    return {"ur": ur, "opw": opw}, {}


def _scale(p: Tensor, M: Tensor) -> float:
    pts = torch.cat((p.detach(), M.detach()[None, :3, 3]))
    return 1.0 + float((pts - pts[0]).norm(dim=-1).max())


def recognise_industrial(chain) -> tuple[str, float]:
    """``(family, scale)`` of a six-revolute chain from its geometry at q = 0; ModelError listing every
    condition checked when it is neither family. Kept on the chain's :class:`~diffkin.kernels.cache.Data`
    (remade with it when a parameter or buffer changes)."""
    data = cache.current(chain, grad=False)
    cached = None if data is None else data.extra.get("closed_form_family")
    if cached is not None:
        return cached
    if chain.n_joints != 6 or chain.joint_types != "RRRRRR" or not chain.single_end:
        raise ModelError(
            f"chain '{chain.name}' ({chain.joint_types}, {chain.n_joints} joints, {chain.n_ends} end "
            "link(s)) "
            "is not a serial six-revolute arm, so neither industrial family (ur, opw) applies"
        )
    with torch.no_grad():
        u, p, M = _zero_lines(chain)
        scale = _scale(p, M)
        checks, _ = _checks(u, p, scale)
    for fam in INDUSTRIAL_FAMILIES:
        if all(ok for _, ok in checks[fam]):
            if data is not None:
                data.extra["closed_form_family"] = (fam, scale)
            return fam, scale
    lines = "; ".join(
        f"{fam}: " + ", ".join(f"{d} {'ok' if ok else 'FAILS'}" for d, ok in checks[fam]) for fam in checks
    )
    raise ModelError(
        f"chain '{chain.name}' fits no closed-form family (joint axes at q = 0, tolerance {_ANGLE_TOL:g} on "
        f"angles, {_LENGTH_TOL:g}·{scale:.3g} m on distances) — {lines}; use diffkin.ik.solve"
    )


def industrial_parameters(chain) -> dict[str, float]:
    """The family's geometric parameters, extracted from the joint lines at q = 0 (no DH table needed).

    ``ur``: ``d1`` (height of axis 2 over the base origin along axis 1), ``a2``, ``a3`` (distances between
    the parallel axes 2–3 and 3–4), ``d4`` (offset along the parallel axes from axis 2 to axis 5), ``d5``
    (from axis 4 to the point where axes 5 and 6 meet) and ``d6`` (from there to the flange, along axis 6).
    ``opw`` (Brandstötter et al. 2014): ``c1`` (axis 2 over the base origin), ``a1`` (axes 1–2), ``c2``
    (axes 2–3), ``c3`` and ``a2`` (wrist centre from axis 3 along / across axis 4 at q = 0, in the arm plane),
    ``b`` (lateral offset along axis 2), ``c4`` (wrist centre to flange along axis 6). Lengths are ≥ 0
    except ``a2``, ``b`` whose sign follows the chain's axes.
    """
    fam, _ = recognise_industrial(chain)
    with torch.no_grad():
        u, p, M = (t.double().cpu() for t in _zero_lines(chain))
    o = chain.base[:3, 3].detach().double().cpu() if chain.base is not None else torch.zeros(3, dtype=p.dtype)
    f1, f2 = _closest(p[0], u[0], p[1], u[1])  # feet of the common normal of axes 1, 2
    x45 = _closest(p[3], u[3], p[4], u[4])[0]
    if fam == "ur":
        x56 = _closest(p[4], u[4], p[5], u[5])[0]
        out = {
            "d1": float((f1 - o) @ u[0]),
            "a2": float(_perp(p[2] - p[1], u[1]).norm()),
            "a3": float(_perp(x45 - p[2], u[1]).norm()),
            "d4": float(abs((x45 - f2) @ u[1])),
            "d5": float((x56 - x45).norm()),
            "d6": float(abs((M[:3, 3] - x56) @ u[5])),
        }
    else:
        r4 = _perp(x45 - p[2], u[1])
        along = u[3] - (u[3] @ u[1]) * u[1]
        along = along / along.norm()
        out = {
            "c1": float((f1 - o) @ u[0]),
            "a1": float((f2 - f1).norm()),
            "c2": float(_perp(p[2] - p[1], u[1]).norm()),
            "c3": float(abs(r4 @ along)),
            "a2": float((r4 - (r4 @ along) * along).norm()),
            "b": float((x45 - f2) @ u[1]),
            "c4": float(abs((M[:3, 3] - x45) @ u[5])),
        }
    return out


# --------------------------------------------------------------------------------------- kernels
def _dot(a: Tensor, b: Tensor) -> Tensor:
    return (a * b).sum(-1)


def _atan2(y: Tensor, x: Tensor, tiny: float) -> Tensor:
    """atan2 that returns 0 with a zero gradient where (y, x) is ~0 (a free angle: singular subproblem)."""
    zero = y * y + x * x <= tiny * tiny
    one = torch.ones_like(x)
    at = torch.atan2(torch.where(zero, 0 * y, y), torch.where(zero, one, x))
    return torch.where(zero, torch.zeros_like(y), at)


def _half_angle(k: Tensor, r2: Tensor, tiny: float, s2: Tensor | None = None) -> Tensor:
    """α = atan2(√(r² − k²), k) ∈ [0, π] (acos(k / r) without the division): the ± half-width of the roots
    of r cos(q − φ) = k. Clamped to 0 / π outside the reachable range, π/2 where r = k = 0; finite gradients.
    ``s2``: r² − k² computed without cancellation by the caller (near a double root), if it can."""
    s2 = r2 - k * k if s2 is None else s2
    pos = s2 > tiny * tiny
    s = torch.where(pos, torch.sqrt(torch.where(pos, s2, torch.ones_like(s2))), torch.zeros_like(s2))
    zero = (~pos) & (k.abs() <= tiny)
    at = torch.atan2(s, torch.where(zero, torch.ones_like(k), k))
    return torch.where(zero, torch.full_like(k, math.pi / 2), at)


def _mv(R: Tensor, v: Tensor) -> Tensor:
    return (R @ v[..., None])[..., 0]


def _sub1(u: Tensor, v: Tensor, w: Tensor, tiny: float) -> Tensor:
    """Paden–Kahan subproblem 1: the angle about the unit axis u taking v to w (same u-components)."""
    return _atan2(_dot(u, cross(v, w)), _dot(v, w) - _dot(u, v) * _dot(u, w), tiny)


def _cos_sin_roots(A: Tensor, B: Tensor, k: Tensor, tiny: float, s2=None) -> tuple[Tensor, Tensor]:
    """The two roots q of A cos q + B sin q = k: φ + α, φ − α with φ = atan2(B, A)."""
    phi = _atan2(B, A, tiny)
    al = _half_angle(k, A * A + B * B, tiny, s2)
    return phi + al, phi - al


def _planar_2r(u2, u3, r3, r4, t, tiny):
    """q_2, q_3 with R(u2, q2)(r3 + R(u3, q3) r4) = t (all ⟂ u2): elbow + and − roots -> ((q2, q3), ...)."""
    A = _dot(r3, r4)
    B = _dot(r3, cross(u3, r4))
    k = 0.5 * (_dot(t, t) - _dot(r3, r3) - _dot(r4, r4))
    out = []
    for q3 in _cos_sin_roots(A.expand_as(k), B.expand_as(k), k, tiny):
        v = r3 + _mv(_axis_angle_to_matrix(u3, q3), r4)
        out.append((_sub1(u2, v, t, tiny), q3))
    return out


def _shoulder(u, p, w, h, tiny):
    """Roots q_1 of n(q_1)·(w − p_1) = h, n(q_1) = R(u_1, q_1) u_2 (w on the parallel-axes side)."""
    rho = w - p[0]
    c12 = u[0] @ u[1]
    A = _dot(rho, u[1] - c12 * u[0])
    B = _dot(rho, torch.linalg.cross(u[0], u[1]).expand_as(rho))
    C = c12 * _dot(rho, u[0].expand_as(rho))
    return _cos_sin_roots(A, B, h - C, tiny)


def _apply(G: Tensor, x: Tensor) -> Tensor:
    """Homogeneous transforms G (..., 4, 4) applied to points x (..., 3)."""
    return _mv(G[..., :3, :3], x) + G[..., :3, 3]


def solve_industrial(chain, family: str, T: Tensor) -> Tensor:
    """All 8 branches ``(..., 8, 6)`` (unwrapped angles) for world targets ``T (..., 4, 4)``."""
    u, p, M = _zero_lines(chain)
    u, p, M = (t.to(T.dtype) for t in (u, p, M))
    tiny = 100.0 * eps_for(T.dtype)
    G = T @ _transform_inverse(M)  # = e^{ξ1 q1} ... e^{ξ6 q6}
    RG = G[..., :3, :3]
    x45 = _closest(p[3], u[3], p[4], u[4])[0]
    r3 = _perp(p[2] - p[1], u[1])
    s3 = torch.sign(u[2] @ u[1])
    u3 = s3 * u[1]  # axis 3 with its sign, exactly parallel to u2 (the 2R problem's plane)
    branches = []
    if family == "ur":
        w0 = _closest(p[4], u[4], p[5], u[5])[0]
        w = _apply(G, w0)
        r4 = _perp(x45 - p[2], u[1])
        c56, c25 = u[4] @ u[5], u[1] @ u[4]
        A5 = u[1] @ u[5] - c56 * c25
        B5 = u[1] @ torch.linalg.cross(u[4], u[5])
        s4 = torch.sign(u[3] @ u[1])
        e = r3 / r3.norm()
        for q1 in _shoulder(u, p, w, (w0 - p[0]) @ u[1], tiny):
            R1 = _axis_angle_to_matrix(u[0], q1)
            n = _mv(R1, u[1])
            v6 = _mv(RG, u[5])
            nv6 = _dot(n, v6)
            m = _mv(RG.transpose(-1, -2), n)  # R6 m = R5^T u2
            # r² − k² = (r² − 1) + |n × v6|² + 2 C n·v6 − C² (C = c56 c25): no cancellation at q5 = 0, π
            C5 = c56 * c25
            cr = cross(n, v6)
            s2 = (A5 * A5 + B5 * B5 - 1.0) + _dot(cr, cr) + 2 * C5 * nv6 - C5 * C5
            for q5 in _cos_sin_roots(A5.expand_as(nv6), B5.expand_as(nv6), nv6 - C5, tiny, s2):
                R5 = _axis_angle_to_matrix(u[4], q5)
                v = _mv(R5.transpose(-1, -2), u[1].expand_as(m))
                q6 = _sub1(u[5], m, v, tiny)
                R6 = _axis_angle_to_matrix(u[5], q6)
                y = _apply(G, _mv(R6.transpose(-1, -2), x45 - p[5]) + p[5])  # axes 4–5 point, world
                y1 = _mv(R1.transpose(-1, -2), y - p[0]) + p[0]
                Rr = R1.transpose(-1, -2) @ RG @ R6.transpose(-1, -2) @ R5.transpose(-1, -2)  # R2 R3 R4
                psi = _sub1(u[1], e.expand_as(y1), _mv(Rr, e), tiny)  # q2 + s3 q3 + s4 q4 about u2
                for q2, q3 in _planar_2r(u[1], u3, r3, r4, _perp(y1 - p[1], u[1]), tiny):
                    q4 = s4 * (psi - q2 - s3 * q3)
                    branches.append(torch.stack((q1, q2, q3, q4, q5, q6), -1))
        return torch.stack(branches, -2)
    # opw
    w0 = x45
    w = _apply(G, w0)
    r4 = _perp(w0 - p[2], u[1])
    u4, u5, u6 = u[3], u[4], u[5]
    c45 = u4 @ u5
    n45 = torch.linalg.cross(u4, u5)
    e6 = torch.linalg.cross(u6, u5)
    e6 = e6 / e6.norm()  # a direction ⟂ u6 to read q6 from
    for q1 in _shoulder(u, p, w, (w0 - p[0]) @ u[1], tiny):
        R1 = _axis_angle_to_matrix(u[0], q1)
        y1 = _mv(R1.transpose(-1, -2), w - p[0]) + p[0]
        for q2, q3 in _planar_2r(u[1], u3, r3, r4, _perp(y1 - p[1], u[1]), tiny):
            R123 = R1 @ _axis_angle_to_matrix(u[1], q2 + s3 * q3)
            Rw = R123.transpose(-1, -2) @ RG  # = R4 R5 R6
            v = _mv(Rw, u6)
            # subproblem 2: z = R5 u6 with z·u4 = v·u4 and z·u5 = u6·u5
            a_, b_ = _dot(v, u4.expand_as(v)), (u6 @ u5).expand_as(v[..., 0])
            det = 1.0 - c45 * c45
            al, be = (a_ - c45 * b_) / det, (b_ - c45 * a_) / det
            # 1 − α² − β² − 2αβ c45, with 1 − (v·u4)² = |u4 × v|²: no cancellation at the wrist singularity
            cr = cross(u4.expand_as(v), v)
            g2 = (_dot(cr, cr) + a_ * a_ - al * al - be * be - 2 * al * be * c45) / (n45 @ n45)
            pos = g2 > tiny * tiny
            g = torch.where(pos, torch.sqrt(torch.where(pos, g2, torch.ones_like(g2))), torch.zeros_like(g2))
            for sgn in (1.0, -1.0):
                z = al[..., None] * u4 + be[..., None] * u5 + (sgn * g)[..., None] * n45
                q5 = _sub1(u5, u6.expand_as(z), z, tiny)
                q4 = _sub1(u4, z, v, tiny)
                R45 = _axis_angle_to_matrix(u4, q4) @ _axis_angle_to_matrix(u5, q5)
                R6 = R45.transpose(-1, -2) @ Rw
                q6 = _sub1(u6, e6.expand_as(z), _mv(R6, e6), tiny)
                branches.append(torch.stack((q1, q2, q3, q4, q5, q6), -1))
    return torch.stack(branches, -2)

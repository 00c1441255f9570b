"""Closed-form inverse kinematics of the textbook's structures (§2.12), batched, every branch at once.

:func:`closed_form` recognises the structure from the DH table (standard convention), not from the name, so a
model with other link lengths, joint offsets ``theta``, a first-row ``d_1``, a base and a tool still works.
Rows are (a, α, d) per joint, ``*`` = any value; k = number of branches:

- ``three_link_planar`` (RRR, Table 2.1): (a1≠0, 0, *), (a2≠0, 0, *), (*, 0, *); (2.90)–(2.92), k = 2
- ``spherical_arm`` (RRP, Table 2.3): (0, −π/2, *), (0, π/2, *), (0, 0, *); (2.94), k = 2
- ``anthropomorphic_arm`` (RRR, Table 2.4): (0, π/2, *), (a2≠0, 0, 0), (a3≠0, 0, 0); (2.95)–(2.110), k = 4
- ``spherical_wrist`` (RRR, Table 2.5): (0, −π/2, *), (0, π/2, 0), (0, 0, *); (2.111)–(2.112), k = 2
- ``stanford`` (RRPRRR, §2.9.6): the spherical-arm rows, then the wrist rows (its d4 any); k = 4
- ``anthropomorphic_wrist`` (RRRRRR, Table 2.6): (0, π/2, *), (a2, 0, 0), (0, π/2, 0), (0, −π/2, d4≠0),
  (0, π/2, 0), (0, 0, *); k = 8

Beyond the book's tables, any serial six-revolute chain (DH in either convention, or URDF) whose geometry
at q = 0 fits one of the industrial families of :mod:`diffkin.ik.industrial` is solved too (k = 8):

- ``ur`` — Universal Robots UR3/5/10/16 and e-series (axes 2, 3, 4 parallel, offset wrist);
- ``opw`` — ortho-parallel basis and spherical wrist with offsets (ABB IRB, KUKA KR, Fanuc, Stäubli,
  Motoman, Puma 560 with a3 / d3).

Six-DOF arms are decoupled at the wrist point p_W = p_e - d_6 a_e (2.93): the arm solves p_W, then the
wrist's ZYZ angles come from R_3^T R_e (§2.12.2).

Unreachable targets are not an error: their branches come back finite (the book's formulas with clamped
arguments) and flagged ``success = False``. ``success`` is decided by forward kinematics: a branch succeeds
when its pose matches the target within ``tol``, so singular targets (infinitely many solutions) still return
one valid representative per branch.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from .._numerics import safe_atan2, safe_sqrt, tol_for, wrap_angle
from .._unchecked import fk
from ..errors import ModelError, ShapeError
from ..kernels.joints import dh_matrix
from ..rotations import _matrix_to_euler
from ..transforms import _transform_inverse
from ..validation import shape_str, tensors
from .industrial import INDUSTRIAL_FAMILIES, recognise_industrial, solve_industrial

__all__ = ["ClosedFormSolution", "closed_form", "identify_structure", "CLOSED_FORM_STRUCTURES", "into_limits"]

_H = math.pi / 2
# structure -> (joint types, alpha, a: None = any / "nz" = nonzero / 0, d: None = any / 0 / "nz", branches)
_TABLES = {
    "three_link_planar": ("RRR", (0, 0, 0), ("nz", "nz", None), (None, None, None), 2),
    "spherical_arm": ("RRP", (-_H, _H, 0), (0, 0, 0), (None, None, None), 2),
    "anthropomorphic_arm": ("RRR", (_H, 0, 0), (0, "nz", "nz"), (None, 0, 0), 4),
    "spherical_wrist": ("RRR", (-_H, _H, 0), (0, 0, 0), (None, 0, None), 2),
    "stanford": ("RRPRRR", (-_H, _H, 0, -_H, _H, 0), (0,) * 6, (None, None, None, None, 0, None), 4),
    "anthropomorphic_wrist": (
        "RRRRRR",
        (_H, 0, _H, -_H, _H, 0),
        (0, "nz", 0, 0, 0, 0),
        (None, 0, 0, "nz", 0, None),
        8,
    ),
}
CLOSED_FORM_STRUCTURES = (*_TABLES, *INDUSTRIAL_FAMILIES)


class _Solution(NamedTuple):
    q: Tensor
    success: Tensor


class ClosedFormSolution(_Solution):
    """All branches of a closed-form solution.

    q: ``(..., k, n)`` joint values: revolute joints in (-π, π], or shifted by ±2π into the joint limits
    where that brings them in; success: ``(..., k)`` bool, True where the branch reproduces the target
    within the tolerance (the result convention of :class:`~diffkin.ik.IKResult`: ``.q`` and ``.success``).
    Unpack as ``q, success = closed_form(chain, T_target)`` (a 2-tuple, as before). Also carries
    ``within_limits`` ``(..., k)`` bool (every joint within the chain's limits; all True without limits)
    and ``structure`` (the recognised structure name).
    """

    def __new__(cls, q: Tensor, success: Tensor, within_limits: Tensor | None = None, structure: str = ""):
        self = super().__new__(cls, q, success)
        self.within_limits = (
            within_limits if within_limits is not None else torch.ones_like(success, dtype=torch.bool)
        )
        self.structure = structure
        return self


# ------------------------------------------------------------------------------------- structure
def _matches(value: float, spec, tol: float) -> bool:
    if spec is None:
        return True
    if spec == "nz":
        return abs(value) > tol
    return abs(value - spec) <= tol


def _angle_matches(value: float, target: float, tol: float) -> bool:
    return abs(math.atan2(math.sin(value - target), math.cos(value - target))) <= tol


def identify_structure(chain) -> str:
    """Name of the structure ``chain`` has: a §2.12 DH table (see the module table) for a standard-DH
    :class:`~diffkin.chain.DHChain`, else (or when none fits) an industrial family (``ur``, ``opw``) from
    the joint geometry of any six-revolute chain; ModelError naming what was checked if none."""
    from ..chain import DHChain

    if not isinstance(chain, DHChain) or chain.convention != "standard":
        if chain.n_joints == 6 and chain.joint_types == "RRRRRR":
            return recognise_industrial(chain)[0]
        raise ModelError(
            "closed-form IK needs a DHChain in the standard (book) DH convention with one of the §2.12 "
            "tables, or a serial six-revolute arm of an industrial family (ur, opw); got "
            f"{type(chain).__name__}{'' if not isinstance(chain, DHChain) else ' (' + chain.convention + ')'}"
            " "
            f"'{chain.name}' ({chain.joint_types})"
        )
    tol = 1e-6
    table = chain.dh_table().double().cpu().tolist()  # rows (a, alpha, d, theta); once per call, not hot
    for name, (types, alphas, a_spec, d_spec, _) in _TABLES.items():
        if chain.joint_types != types:
            continue
        if all(
            _angle_matches(row[1], al, tol) and _matches(row[0], sa, tol) and _matches(row[2], sd, tol)
            for row, al, sa, sd in zip(table, alphas, a_spec, d_spec)
        ):
            return name
    if chain.n_joints == 6 and chain.joint_types == "RRRRRR":
        try:
            return recognise_industrial(chain)[0]
        except ModelError as err:
            raise ModelError(
                f"chain '{chain.name}' has no closed-form solution here: its DH table matches none of "
                f"{', '.join(_TABLES)} (§2.12), and {err}"
            ) from None
    raise ModelError(
        f"chain '{chain.name}' ({chain.joint_types}, {chain.n_joints} joints) has no closed-form solution "
        f"here: its DH table matches none of {', '.join(_TABLES)} (§2.12), and only six-revolute arms can "
        f"be of the industrial families ({', '.join(INDUSTRIAL_FAMILIES)}); use diffkin.ik.solve"
    )


# ------------------------------------------------------------------------------------ book kernels


def planar_3r(px: Tensor, py: Tensor, phi: Tensor, a1, a2, a3) -> Tensor:
    """ϑ of the three-link planar arm (2.90)–(2.92): branches ``(..., 2, 3)``, s2 ≥ 0 (elbow down) first."""
    pwx, pwy = px - a3 * torch.cos(phi), py - a3 * torch.sin(phi)
    c2 = ((pwx * pwx + pwy * pwy - a1 * a1 - a2 * a2) / (2 * a1 * a2)).clamp(-1.0, 1.0)
    out = []
    for sign in (1.0, -1.0):
        s2 = sign * safe_sqrt(1.0 - c2 * c2)
        th2 = torch.atan2(s2, c2)
        k1, k2 = a1 + a2 * c2, a2 * s2
        # s1, c1 times the positive p_W^2, which atan2 does not need
        th1 = safe_atan2(k1 * pwy - k2 * pwx, k1 * pwx + k2 * pwy)
        out.append(torch.stack((th1, th2, phi - th1 - th2), dim=-1))
    return torch.stack(out, dim=-2)


def spherical_arm_position(p: Tensor, d2) -> Tensor:
    """(ϑ1, ϑ2, d3) of the spherical arm for the wrist point p (..., 3) in frame 0 (2.94): ``(..., 2, 3)``.

    ϑ1 solves -p_x s1 + p_y c1 = d2 (third row of (2.94)); written as ϑ1 = Atan2(p_y, p_x) -
    Atan2(d2, ±√(p_x² + p_y² - d2²)), the same two roots as the book's half-angle formula without its 0/0
    cases. Then d3 = √((p_x c1 + p_y s1)² + p_z²) ≥ 0 and ϑ2 = Atan2(p_x c1 + p_y s1, p_z).
    """
    px, py, pz = p.unbind(-1)
    rho2 = px * px + py * py
    root = safe_sqrt((rho2 - d2 * d2).clamp_min(0.0))
    d2t = torch.as_tensor(d2, dtype=p.dtype, device=p.device).expand_as(px)
    out = []
    for sign in (1.0, -1.0):
        th1 = safe_atan2(py, px) - safe_atan2(d2t, sign * root)
        u = px * torch.cos(th1) + py * torch.sin(th1)
        out.append(torch.stack((th1, safe_atan2(u, pz), safe_sqrt(u * u + pz * pz)), dim=-1))
    return torch.stack(out, dim=-2)


def anthropomorphic_arm_position(p: Tensor, a2, a3) -> Tensor:
    """ϑ of the anthropomorphic arm for the wrist point p (..., 3) (2.98)–(2.110): ``(..., 4, 3)``.

    Order as in the book: (ϑ1I, ϑ2I, ϑ3I), (ϑ1I, ϑ2III, ϑ3II), (ϑ1II, ϑ2II, ϑ3I), (ϑ1II, ϑ2IV, ϑ3II).
    """
    px, py, pz = p.unbind(-1)
    rho = safe_sqrt(px * px + py * py)
    c3 = ((px * px + py * py + pz * pz - a2 * a2 - a3 * a3) / (2 * a2 * a3)).clamp(-1.0, 1.0)
    s3_abs = safe_sqrt(1.0 - c3 * c3)
    k = a2 + a3 * c3
    out = []
    for shoulder in (1.0, -1.0):  # sign of (2.102): ϑ1I = Atan2(py, px), ϑ1II = Atan2(-py, -px)
        th1 = safe_atan2(shoulder * py, shoulder * px)
        for elbow in (1.0, -1.0):  # s3+ / s3-
            s3 = elbow * s3_abs
            r = shoulder * rho
            th2 = safe_atan2(k * pz - a3 * s3 * r, k * r + a3 * s3 * pz)
            out.append(torch.stack((th1, th2, torch.atan2(s3, c3)), dim=-1))
    return torch.stack(out, dim=-2)


def spherical_wrist_orientation(R: Tensor) -> Tensor:
    """ZYZ angles (ϑ4, ϑ5, ϑ6) of R_6^3 (2.111)–(2.112): ``(..., 2, 3)``, ϑ5 ∈ (0, π) first, then (-π, 0)."""
    return torch.stack([_matrix_to_euler(R, "ZYZ", b) for b in ("positive", "negative")], dim=-2)


# ----------------------------------------------------------------------------------- DH products
def _fk0(chain, theta: Tensor, d: Tensor, upto: int) -> Tensor:
    """T_upto^0 (no base, no tool) from full DH angles/offsets ``(..., n)``; may hold only the first
    ``upto`` joints (the wrist-centre step), so it cannot use the chain's whole-chain kernel."""
    T = None
    for i in range(upto):
        A = dh_matrix(chain.a[i], chain.alpha[i], d[..., i], theta[..., i])  # (2.52)
        T = A if T is None else T @ A
    return T


# ------------------------------------------------------------------------------------- targets
def _target_frame0(chain, T: Tensor) -> Tensor:
    """World pose of the end effector -> T_n^0 (base and tool removed)."""
    if chain.base is not None:
        T = _transform_inverse(chain.base) @ T
    if chain.tool is not None:
        T = T @ _transform_inverse(chain.tool)
    return T


def _tool_translation_free(chain, what: str) -> None:
    if chain.tool is not None and bool(chain.tool[:3, 3].abs().max() > 0):
        raise ModelError(
            f"chain '{chain.name}' has a tool with a translation, so a {what} target does not fix the last "
            "DH frame; pass a full pose (..., 4, 4)"
        )


def _position_frame0(chain, p: Tensor) -> Tensor:
    _tool_translation_free(chain, "position")
    if chain.base is None:
        return p
    Rb, pb = chain.base[:3, :3], chain.base[:3, 3]
    return torch.einsum("ji,...j->...i", Rb, p - pb)


def _rotation_frame0(chain, R: Tensor) -> Tensor:
    if chain.base is not None:
        R = chain.base[:3, :3].T @ R
    if chain.tool is not None:
        R = R @ chain.tool[:3, :3].T
    return R


def _planar_frame0(chain, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """(p_x, p_y, φ) of the end effector in the world -> origin and angle of frame 3 in frame 0."""
    px, py, phi = x.unbind(-1)
    if chain.base is not None:
        B = chain.base
        if float((B[2, 2] - 1).abs()) > 1e-9:
            raise ModelError("a planar (p_x, p_y, phi) target needs a base rotated about z only; pass a pose")
        yaw = torch.atan2(B[1, 0], B[0, 0])
        c, s = torch.cos(yaw), torch.sin(yaw)
        dx, dy = px - B[0, 3], py - B[1, 3]
        px, py, phi = c * dx + s * dy, -s * dx + c * dy, phi - yaw
    if chain.tool is not None:
        t = chain.tool[:3, 3]
        c, s = torch.cos(phi), torch.sin(phi)
        px, py = px - (c * t[0] - s * t[1]), py - (s * t[0] + c * t[1])
    return px, py, phi


# ------------------------------------------------------------------------------------------- API
def _check_target(T, chain) -> Tensor:
    """The target by the rule of :mod:`diffkin.validation` (the chain's dtype and device, finite)."""
    return tensors(("T", T, None), like=chain)[0]


def _kind(T: Tensor, structure: str) -> str:
    if T.ndim >= 2 and tuple(T.shape[-2:]) == (4, 4):
        return "pose"
    if structure == "spherical_wrist" and T.ndim >= 2 and tuple(T.shape[-2:]) == (3, 3):
        return "rotation"
    if (
        structure in ("three_link_planar", "spherical_arm", "anthropomorphic_arm")
        and T.ndim >= 1
        and (T.shape[-1] == 3)
    ):
        return "planar" if structure == "three_link_planar" else "position"
    expected = {
        "three_link_planar": "(..., 4, 4) or (p_x, p_y, phi) (..., 3)",
        "spherical_arm": "(..., 4, 4) or a position (..., 3)",
        "anthropomorphic_arm": "(..., 4, 4) or a position (..., 3)",
        "spherical_wrist": "(..., 4, 4) or a rotation (..., 3, 3)",
    }.get(structure, "(..., 4, 4)")
    raise ShapeError(
        f"expected a target T of shape {expected} for a {structure}, got {shape_str(T.shape)}"
    )


def _z(d1: Tensor) -> Tensor:
    zero = torch.zeros_like(d1)
    return torch.stack((zero, zero, d1))


def _expand(v: Tensor, like: Tensor) -> Tensor:
    """(n,) chain values -> (..., k, n) like the branches."""
    return v.expand(*like.shape[:-1], v.shape[-1])


def _solve_theta(chain, structure: str, kind: str, T: Tensor):
    """Full DH angles and offsets ``(..., k, n)`` of every branch, and the frame-0 target for the check."""
    a, d = chain.a, chain.d
    T0 = _target_frame0(chain, T) if kind == "pose" else None
    if structure == "three_link_planar":
        if kind == "pose":
            px, py, phi = T0[..., 0, 3], T0[..., 1, 3], torch.atan2(T0[..., 1, 0], T0[..., 0, 0])
            ref = T0
        else:
            px, py, phi = ref = _planar_frame0(chain, T)
        th = planar_3r(px, py, phi, a[0], a[1], a[2])
        return th, _expand(d, th), ref
    if structure == "spherical_wrist":
        R0 = T0[..., :3, :3] if kind == "pose" else _rotation_frame0(chain, T)
        th = spherical_wrist_orientation(R0)
        return th, _expand(d, th), (T0 if kind == "pose" else R0)
    if structure in ("spherical_arm", "anthropomorphic_arm"):
        p0 = T0[..., :3, 3] if kind == "pose" else _position_frame0(chain, T)
        if structure == "anthropomorphic_arm":
            th = anthropomorphic_arm_position(p0 - _z(d[0]), a[1], a[2])
            return th, _expand(d, th), p0
        th, dd = _spherical_arm_full(chain, p0 - _z(d[0]), 0.0)
        return th, dd, p0
    # six DOF: wrist point (2.93), arm, then the wrist's ZYZ angles of R_3^T R (§2.12.2)
    pw = T0[..., :3, 3] - d[5] * T0[..., :3, 2] - _z(d[0])
    if structure == "stanford":
        th, dd = _spherical_arm_full(chain, pw, d[3])  # the wrist point sits d4 beyond frame 3 along z2
    else:
        th = anthropomorphic_arm_position(pw, a[1], d[3])
        th = torch.cat((th[..., :2], th[..., 2:] + _H), dim=-1)  # frame 3 of Fig. 2.26 vs Fig. 2.23
        dd = _expand(d[:3], th)
    R36 = _fk0(chain, th, dd, 3)[..., :3, :3].transpose(-1, -2) @ T0[..., None, :3, :3]
    wrist = spherical_wrist_orientation(R36)  # (..., k_arm, 2, 3)
    k = 2 * th.shape[-2]
    th = torch.cat((th.unsqueeze(-2).expand_as(wrist), wrist), dim=-1).reshape(*th.shape[:-2], k, 6)
    dd = dd.unsqueeze(-2).expand_as(wrist).reshape(*th.shape[:-2], k, 3)
    return th, torch.cat((dd, _expand(d[3:], dd)), dim=-1), T0


def _spherical_arm_full(chain, p: Tensor, extra) -> tuple[Tensor, Tensor]:
    """Spherical-arm branches as full (theta, d) of joints 1–3; ``extra`` is subtracted from d3."""
    sol = spherical_arm_position(p, chain.d[1])
    th3 = chain.theta[2].expand_as(sol[..., :1])
    th = torch.cat((sol[..., :2], th3), dim=-1)
    dd = torch.cat((chain.d[0].expand_as(th3), chain.d[1].expand_as(th3), sol[..., 2:] - extra), dim=-1)
    return th, dd


def _to_joints(chain, th: Tensor, dd: Tensor) -> Tensor:
    """Full DH (angles, offsets) -> joints: ϑ - theta wrapped (revolute), d - d_offset (prismatic)."""
    rev = chain.revolute_mask
    return rev * wrap_angle(th - chain.theta) + (1.0 - rev) * (dd - chain.d)


def into_limits(chain, q: Tensor) -> Tensor:
    """Revolute joints of ``q (..., n)`` wrapped to (-π, π], then, where a joint is outside its limits and
    q + 2πk lies inside for some integer k, shifted there (the smallest such value); others unchanged."""
    rev = chain.revolute_mask.bool()
    qw = torch.where(rev, wrap_angle(q), q)
    if chain.q_limits is None:
        return qw
    lo, hi = chain.q_limits[:, 0].to(q.dtype), chain.q_limits[:, 1].to(q.dtype)
    inside = (qw >= lo) & (qw <= hi)
    lo_f = torch.where(torch.isfinite(lo), lo, torch.zeros_like(lo))
    alt = lo_f + torch.remainder(qw - lo_f, 2 * math.pi)  # smallest value >= lo congruent to q
    use = rev & ~inside & torch.isfinite(lo) & (alt <= hi)
    return torch.where(use, alt, qw)


def closed_form(chain, T_target: Tensor, tol: float | None = None) -> ClosedFormSolution:
    """Every closed-form IK branch of a §2.12 structure: ``q (..., k, n)`` and ``success (..., k)``.

    Args:
        chain: a standard-DH :class:`~diffkin.chain.DHChain` with one of the tables listed in the module
            docstring (recognised by structure; any link lengths, joint offsets, ``d_1``, base and tool), or
            any six-revolute chain (DH, modified DH, URDF) of the ``ur`` / ``opw`` families (recognised from
            its joint geometry at q = 0, base and tool folded in; see :mod:`diffkin.ik.industrial`).
        T_target: target in the world frame (before the chain's base, after its tool):

            - any structure: an end-effector pose ``(..., 4, 4)``;
            - ``three_link_planar``: or ``(..., 3)`` = (p_x, p_y, φ), end-effector position and the angle of
              x_3 from x_0 (2.90) (a base must rotate about z only);
            - ``spherical_arm`` / ``anthropomorphic_arm``: or a wrist position ``(..., 3)`` (the book's p_W;
              these 3-DOF arms are solved and checked on position only, also from a pose);
            - ``spherical_wrist``: or a rotation ``(..., 3, 3)``.
        tol: validity tolerance (position scaled by the arm's size, rotation by the matrix norm); default
            1e-6 (float64) / 1e-3 (float32).

    Branch order (k): planar s2 ≥ 0 then s2 ≤ 0; anthropomorphic arm as the book (2.110); spherical arm and
    wrist ± roots; six-DOF arms: arm branch major, wrist ϑ5 > 0 then ϑ5 < 0; ``ur``: shoulder, wrist,
    elbow; ``opw``: shoulder, elbow, wrist (see :mod:`diffkin.ik.industrial`, also for singular targets).
    Revolute joints are returned in (-π, π] after removing the DH offsets, or shifted by a multiple of 2π
    into the joint limits where one exists (:func:`into_limits`; ``within_limits`` flags the branches inside
    the limits); prismatic joint values are d - d_offset.

    Differentiable w.r.t. ``T_target`` and the chain's geometry (autograd through the formulas; finite
    gradients at singular targets). Batched over leading dims, float32/float64, on the target's device.
    """
    structure = identify_structure(chain)
    T = _check_target(T_target, chain)
    if structure in INDUSTRIAL_FAMILIES:
        if T.ndim < 2 or tuple(T.shape[-2:]) != (4, 4):
            raise ShapeError(f"expected a target T of shape (..., 4, 4) for a {structure} arm, got "
                             f"{shape_str(T.shape)}")
        q = into_limits(chain, solve_industrial(chain, structure, T))
        valid = _valid_world(chain, q, T, tol)
        return ClosedFormSolution(q, valid, chain.within_limits(q, check=False), structure)
    kind = _kind(T, structure)
    th, dd, ref = _solve_theta(chain, structure, kind, T)
    valid = _valid(chain, structure, kind, th, dd, ref, tol)
    q = into_limits(chain, _to_joints(chain, th, dd))
    return ClosedFormSolution(q, valid, chain.within_limits(q, check=False), structure)


def _valid_world(chain, q: Tensor, T: Tensor, tol) -> Tensor:
    """FK of every branch (world, base and tool included) against the target (scaled as :func:`_valid`)."""
    if tol is None:
        tol = tol_for(T, 1e-6, 1e-3)
    scale = recognise_industrial(chain)[1]
    with torch.no_grad():
        Tq = fk(chain, q.detach())
    dp = (Tq[..., :3, 3] - T[..., None, :3, 3].detach()).norm(dim=-1)
    dr = (Tq[..., :3, :3] - T[..., None, :3, :3].detach()).flatten(-2).norm(dim=-1)
    return (dp <= tol * scale) & (dr <= tol)


def _valid(chain, structure, kind, th_full, d_full, ref, tol) -> Tensor:
    """FK of every branch (frame 0, no base/tool) against the frame-0 target."""
    if tol is None:
        tol = tol_for(chain.dtype, 1e-6, 1e-3)
    scale = 1.0 + float(chain.a.detach().abs().sum() + chain.d.detach().abs().sum())
    Tn = _fk0(chain, th_full, d_full, chain.n_joints)
    if kind == "pose" and structure not in ("spherical_arm", "anthropomorphic_arm"):
        dp = (Tn[..., :3, 3] - ref[..., None, :3, 3]).norm(dim=-1)
        dr = (Tn[..., :3, :3] - ref[..., None, :3, :3]).flatten(-2).norm(dim=-1)
        return (dp <= tol * scale) & (dr <= tol)
    if structure == "spherical_wrist":
        return (Tn[..., :3, :3] - ref[..., None, :, :]).flatten(-2).norm(dim=-1) <= tol
    if structure == "three_link_planar":
        px, py, phi = ref
        dp = torch.hypot(Tn[..., 0, 3] - px[..., None], Tn[..., 1, 3] - py[..., None])
        dphi = wrap_angle(torch.atan2(Tn[..., 1, 0], Tn[..., 0, 0]) - phi[..., None]).abs()
        return (dp <= tol * scale) & (dphi <= tol)
    return (Tn[..., :3, 3] - ref[..., None, :]).norm(dim=-1) <= tol * scale

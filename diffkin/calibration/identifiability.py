"""Identifiability of the calibration parameters and informative pose selection (§2.11).

A parameter is *unidentifiable* when its column of the stacked calibration matrix Φ̄ (2.87) is (numerically)
a linear combination of the columns before it: then (Φ̄ᵀΦ̄)⁻¹ in (2.88) does not exist and the estimate would
drift along the null space. Columns are taken in the order of ζ (DH: a, α, d, ϑ joint by joint kind, then
base, then tool; error models on the chain's parameters: the order of its parameters), normalised to unit
length, and orthogonalised one after the other (Gram–Schmidt with re-orthogonalisation, every row of every
pose: the rank is right also with fewer equations than parameters): the residual of column j after projection
on the span of the kept ones before it (= |R_jj| of an unpivoted QR); below ``rank_tol`` the column is
dependent. So when a base or tool correction duplicates a DH parameter, the DH parameter is kept.

Two analyses: *structural* — Φ̄ at many random configurations — finds the parameters no pose set can
identify (the model's redundancies); they are fixed at nominal and reported with the dependency. *From these
poses* — Φ̄ of the measured configurations — finds those that the data does not determine (too few or too
similar poses): they are **not** frozen; the solvers take minimum-norm steps in the span the data determines
(rank-revealing damped least squares), and the report lists them as ``undetermined`` with
``more_poses_needed`` (the missing rank over the rows per pose).

Observability indices (Borm & Menq 1991; Nahvi & Hollerbach 1996) of the identifiable columns, with
σ_1 ≥ … ≥ σ_L the singular values of the weighted Φ̄ in its own units (metres per metre, metres per
radian) and N poses: O1 = (σ_1 ⋯ σ_L)^(1/L) / √N, O3 = σ_L. The condition number is that of the
column-normalised matrix (what the least-squares solve sees).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from numbers import Integral

import numpy as np
import torch
from torch import Tensor

from .._numerics import eps_for
from ..chain import DHChain
from ..errors import DTypeError, ShapeError
from ..validation import shape_str, tensors
from .model import CalibrationModel, check_measurements

__all__ = ["IdentifiabilityReport", "identifiability", "select_poses", "analyse_matrices", "merge_reports"]


@dataclass
class IdentifiabilityReport:
    """Which candidate parameters the poses determine, and how well.

    ``unidentifiable``: names fixed at nominal; ``reasons[name]``: why (which columns it depends on);
    ``dependencies[name]``: the coefficients c with Φ_name ≈ Σ c_k Φ_k (units of name per unit of k).
    """

    candidates: list[str]
    identifiable: list[str]
    unidentifiable: list[str]
    reasons: dict[str, str]
    dependencies: dict[str, dict[str, float]]
    rank: int
    condition_number: float
    o1: float
    o3: float
    singular_values: list[float]
    n_poses: int
    rank_tol: float
    free_mask: Tensor = field(repr=False)
    #: structurally identifiable but not determined by these poses (minimum-norm estimate, not frozen)
    undetermined: list[str] = field(default_factory=list)
    #: rank the model can reach with enough poses (candidates minus structural redundancies)
    structural_rank: int | None = None
    #: lower bound on the extra poses that could determine the undetermined ones (missing rank / rows
    #: per pose)
    more_poses_needed: int = 0

    def as_dict(self) -> dict:
        """JSON-friendly summary (no tensors)."""
        return {k: v for k, v in self.__dict__.items() if k != "free_mask"}

    def summary(self) -> str:
        lines = [
            f"identifiable {self.rank} of {len(self.candidates)} candidate parameters "
            f"from {self.n_poses} poses; "
            f"condition number {self.condition_number:.3g}, O1 {self.o1:.3g}, O3 {self.o3:.3g}",
        ]
        lines += [f"  fixed at nominal: {self.reasons[nm]}" for nm in self.unidentifiable]
        if self.undetermined:
            lines.append(
                f"  not determined by these poses (rank {self.rank} of {self.structural_rank}; minimum-norm "
                f"estimate): {', '.join(self.undetermined)}; at least {self.more_poses_needed} more "
                f"well-spread pose(s) would help (watch O1/O3 grow)"
            )
        return "\n".join(lines)


def _default_rank_tol(dtype: torch.dtype) -> float:
    # 1e-6 in float64, ~1e-3 in float32: a column whose own direction is below this fraction of its norm
    # amplifies measurement noise by > 1/rank_tol and is treated as dependent.
    return max(1e-6, 1e4 * eps_for(dtype))


def _reason(name: str, coeffs: dict[str, float], residual: float) -> str:
    if not coeffs:
        return f"{name}: has no effect on the measured poses (zero column of the calibration matrix)"
    terms = " ".join(f"{c:+.4g}·{k}" for k, c in coeffs.items())
    return f"{name}: its effect equals {terms} (linearly dependent; residual {residual:.1e})"


def _reports_of_group(Phi, A, R, norms, zero, pattern, names, n_poses, rank_tol, diag):
    """Reports of robots sharing one dependency pattern; all tensors are that group's ``(G, ...)``."""
    keep = (~pattern).nonzero().flatten()
    G = Phi.shape[0]
    if keep.numel():
        s_unit = torch.linalg.svdvals(A[..., keep])
        s = torch.linalg.svdvals(Phi[..., keep])
        cond = (s_unit[:, 0] / s_unit[:, -1]).tolist()
        o1 = (torch.exp(torch.log(s).mean(-1)) / math.sqrt(n_poses)).tolist()
        o3, s = s[:, -1].tolist(), s.tolist()
    else:
        cond, o1, o3, s = [math.inf] * G, [0.0] * G, [0.0] * G, [[]] * G
    deps = [{} for _ in range(G)]
    for j in pattern.nonzero().flatten().tolist():
        prior = keep[keep < j]
        c = torch.zeros(G, 0, dtype=Phi.dtype, device=Phi.device)
        if prior.numel():
            c = torch.linalg.lstsq(R[..., prior], R[..., j : j + 1]).solution[..., 0]
            c = c * norms[:, j : j + 1] / norms[:, prior]  # back to the parameters' own units
        big = c.abs() > 1e-6 * (c.abs().amax(-1, keepdim=True) if prior.numel() else c.new_zeros(G, 1))
        c_list, big_list, z = c.tolist(), big.tolist(), zero[:, j].tolist()
        for g in range(G):
            deps[g][names[j]] = {} if z[g] else {
                names[k]: ck for k, ck, b in zip(prior.tolist(), c_list[g], big_list[g]) if b
            }
    ident = [names[k] for k in keep.tolist()]
    unid = [names[j] for j in pattern.nonzero().flatten().tolist()]
    d = diag.tolist()
    return [
        IdentifiabilityReport(
            candidates=list(names), identifiable=ident, unidentifiable=unid,
            reasons={nm: _reason(nm, deps[g][nm], d[g][names.index(nm)]) for nm in unid},
            dependencies=deps[g], rank=len(ident), condition_number=cond[g], o1=o1[g], o3=o3[g],
            singular_values=s[g], n_poses=n_poses, rank_tol=rank_tol, free_mask=~pattern,
        )
        for g in range(G)
    ]


def _sequential_residuals(A: Tensor, tol: float) -> Tensor:
    """Residual norm of each unit column of ``A (K, rows, L)`` after projection on the span of the columns
    before it that were themselves above ``tol`` (classical Gram–Schmidt, applied twice)."""
    K, rows, L = A.shape
    Q = A.new_zeros(K, rows, L)
    out = A.new_zeros(K, L)
    for j in range(L):
        r = A[..., j]
        for _ in range(2):
            r = r - (Q[..., :j] @ (Q[..., :j].mT @ r[..., None]))[..., 0]
        nr = r.norm(dim=-1)
        out[:, j] = nr
        keep = nr > tol
        Q[..., j] = torch.where(keep[:, None], r / nr.clamp_min(torch.finfo(A.dtype).tiny)[:, None], 0.0)
    return out


def analyse_matrices(
    Phi: Tensor, names: list[str], n_poses: int, rank_tol: float | None = None
) -> list[IdentifiabilityReport]:
    """Identifiability of the columns of K stacked calibration matrices ``Phi (K, rows, L)`` named ``names``.

    Robots with the same dependency pattern are analysed together (batched QR, SVD and least squares).
    """
    Phi = Phi.detach()
    K, rows, L = Phi.shape
    rank_tol = _default_rank_tol(Phi.dtype) if rank_tol is None else rank_tol
    norms = Phi.norm(dim=-2)  # (K, L)
    zero = norms <= rank_tol * norms.amax(-1, keepdim=True).clamp_min(torch.finfo(Phi.dtype).tiny)
    safe = torch.where(zero, torch.ones_like(norms), norms)
    A = torch.where(zero[:, None, :], torch.zeros_like(Phi), Phi / safe[:, None, :])
    diag = _sequential_residuals(A, rank_tol)  # |R_jj|: residual of column j after the kept ones before it
    R = A  # dependencies are solved on the unit-norm columns themselves
    dependent = (diag <= rank_tol) | zero
    patterns, group = torch.unique(dependent, dim=0, return_inverse=True)
    reports: list = [None] * K
    for g, pattern in enumerate(patterns):
        idx = (group == g).nonzero().flatten()
        sub = _reports_of_group(Phi[idx], A[idx], R[idx], norms[idx], zero[idx], pattern, names, n_poses,
                                rank_tol, diag[idx])
        for k, rep in zip(idx.tolist(), sub):
            reports[k] = rep
    return reports


def merge_reports(data: list[IdentifiabilityReport], struct: list[IdentifiabilityReport] | None,
                  candidates: list[str], rows_per_pose: int, device) -> tuple[list[IdentifiabilityReport],
                                                                             Tensor]:
    """One report per robot from the analysis at the data's poses (``data``) and the structural one
    (``struct``, None when no column was analysed structurally), for models whose candidates are reported
    in another order than θ's (e.g. the camera's and board's poses first): the structural redundancies are
    fixed (``unidentifiable``, with reasons), what only these poses leave open is ``undetermined``; the
    free mask ``(K, C)`` follows ``candidates`` (θ's order). ``rows_per_pose``: measured rows per pose, for
    ``more_poses_needed``."""
    reports, free = [], []
    for k, rep in enumerate(data):
        st = struct[k] if struct is not None else None
        fixed = [] if st is None else list(st.unidentifiable)
        fixed_set = set(fixed)
        rep.undetermined = [nm for nm in rep.unidentifiable if nm not in fixed_set]
        rep.structural_rank = len(candidates) - len(fixed)
        missing = rep.structural_rank - rep.rank
        rep.more_poses_needed = math.ceil(missing / max(rows_per_pose, 1)) if missing > 0 else 0
        rep.unidentifiable = fixed
        rep.reasons = {nm: st.reasons[nm] + " at every configuration" for nm in fixed}
        rep.dependencies = {} if st is None else st.dependencies
        rep.candidates = list(candidates)
        undetermined = set(rep.undetermined)
        rep.identifiable = [nm for nm in candidates if nm not in fixed_set and nm not in undetermined]
        rep.free_mask = torch.tensor([nm not in fixed_set for nm in candidates], device=device)
        free.append(rep.free_mask)
        reports.append(rep)
    return reports, torch.stack(free)


def _random_configurations(model, M: int, dtype, device) -> Tensor:
    """``(M, nq)`` reproducible configurations of the nominal chain (the one sampler, a fixed seed) for the
    structural analysis."""
    q = model.chains[0].random_configuration(M, generator=torch.Generator().manual_seed(20251129))
    return q.detach().to(dtype=dtype, device=device)


def model_reports(
    model: CalibrationModel,
    zeta: Tensor,
    q: Tensor,
    position_only: bool,
    orientation_weight: float,
    rank_tol: float | None = None,
) -> tuple[list[IdentifiabilityReport], Tensor]:
    """Reports of K robots (``zeta (K, P)``, ``q (K, N, n)``) and their free mask ``(K, C)`` over the C
    candidate parameters: structural redundancies (random configurations) are fixed; parameters only the
    given poses leave undetermined stay free (minimum-norm estimate) and are listed as ``undetermined``."""
    K, N = q.shape[0], q.shape[1]
    names = [model.names[j] for j in model.candidate.nonzero().flatten().tolist()]
    C = len(names)
    m = 3 if position_only else 6
    with torch.no_grad():
        Phi, _ = model.calibration_matrix(zeta, q, position_only, orientation_weight, columns=model.candidate)
        data = analyse_matrices(Phi.reshape(K, -1, C), names, N, rank_tol)
        M = 2 * math.ceil(C / m) + 8
        qs = _random_configurations(model, M, zeta.dtype, zeta.device).expand(K, M, q.shape[-1])
        Phi_s, _ = model.calibration_matrix(zeta, qs, position_only, orientation_weight,
                                            columns=model.candidate)
        struct = analyse_matrices(Phi_s.reshape(K, -1, C), names, M, rank_tol)
    reports = []
    for rep, st in zip(data, struct):
        fixed = set(st.unidentifiable)
        undetermined = [nm for nm in rep.unidentifiable if nm not in fixed]
        missing = st.rank - rep.rank
        rep.undetermined = undetermined
        rep.structural_rank = st.rank
        rep.more_poses_needed = math.ceil(missing / m) if missing > 0 else 0
        rep.unidentifiable = list(st.unidentifiable)
        rep.reasons = {nm: st.reasons[nm] + " at every configuration" for nm in st.unidentifiable}
        rep.dependencies = st.dependencies
        rep.free_mask = st.free_mask
        reports.append(rep)
    free = torch.stack([rep.free_mask for rep in reports]).to(zeta.device)
    return reports, free


def identifiability(
    chain: DHChain,
    q: Tensor,
    T: Tensor | None = None,
    *,
    parameters="all",
    base: bool = False,
    tool: bool = False,
    joint_offsets: bool = True,
    position_only: bool | None = None,
    orientation_weight: float = 0.1,
    rank_tol: float | None = None,
    error_model: str = "auto",
) -> IdentifiabilityReport:
    """Identifiability report of the nominal ``chain`` for joint readings ``q (N, n)``.

    Only the joint readings matter (Φ̄ is evaluated at the nominal parameters); pass the measurements ``T``
    (``(N, 4, 4)`` or ``(N, 3)``) or ``position_only`` to say which rows are measured (default full pose).
    Parameter selection and ``error_model`` as in :func:`diffkin.calibration.calibrate`.
    """
    from .error_models import build_model

    model, _ = build_model(chain, error_model, parameters, base, tool, joint_offsets)
    if T is not None:
        q, _, position_only = check_measurements(q, T, chain.n_joints, chain)
    else:
        (q,) = tensors(("q", q, (chain.n_joints,)), like=chain)
        if q.ndim != 2 or q.shape[0] < 1:
            raise ShapeError(
                f"expected q of shape (N, {chain.n_joints}) with N >= 1 poses, got {shape_str(q.shape)}"
            )
    reports, _ = model_reports(
        model, model.nominal[None], q[None], bool(position_only), orientation_weight, rank_tol
    )
    return reports[0]


def _indices(initial, M: int) -> list[int]:
    """``initial`` as a list of distinct candidate indices in 0..M-1 (typed errors otherwise)."""
    arr = np.asarray(initial.detach().cpu() if isinstance(initial, Tensor) else initial)
    if arr.dtype.kind not in "iu" or arr.ndim != 1:
        raise DTypeError(f"expected initial as a 1-d sequence of integer indices, got {arr.dtype} of shape "
                         f"{shape_str(arr.shape)}")
    out = arr.tolist()
    if any(not 0 <= i < M for i in out) or len(set(out)) != len(out):
        raise ShapeError(f"initial must hold distinct indices in 0..{M - 1}, got {out}")
    return out


def select_poses(
    chain: DHChain,
    candidates: Tensor,
    k: int,
    *,
    parameters="all",
    base: bool = False,
    tool: bool = False,
    joint_offsets: bool = True,
    position_only: bool = False,
    orientation_weight: float = 0.1,
    initial: Tensor | None = None,
    rank_tol: float | None = None,
    error_model: str = "auto",
) -> Tensor:
    """Greedily pick ``k`` informative configurations among ``candidates (M, n)``; returns indices ``(k,)``.

    Each step adds the candidate that most increases log det(Φ̄ᵀΦ̄ + εI) over the parameters identifiable
    from all candidates (D-optimal design; for a fixed pose count this maximises O1 = (∏σ)^(1/L)/√N, and it
    does not depend on the units of the parameters). ``initial``: indices already chosen.
    """
    (candidates,) = tensors(("candidates", candidates, (chain.n_joints,)), like=chain)
    if candidates.ndim != 2:
        raise ShapeError(
            f"expected candidates of shape (M, {chain.n_joints}), got {shape_str(candidates.shape)}"
        )
    M = candidates.shape[0]
    if isinstance(k, bool) or not isinstance(k, Integral) or not 0 < k <= M:
        raise ShapeError(f"k must be an integer in 1..{M} (the number of candidates), got {k!r}")
    chosen = [] if initial is None else _indices(initial, M)
    if len(chosen) > k:
        raise ShapeError(f"initial holds {len(chosen)} indices, more than k = {k}")
    from .error_models import build_model

    model, _ = build_model(chain, error_model, parameters, base, tool, joint_offsets)
    with torch.no_grad():
        Phi, _ = model.calibration_matrix(
            model.nominal, candidates, position_only, orientation_weight, columns=model.candidate
        )
        _, free = model_reports(
            model, model.nominal[None], candidates[None], position_only, orientation_weight, rank_tol
        )
        G = Phi[..., free[0]]  # (M, m, L)
        L = G.shape[-1]
        eps = 1e-9 * float((G * G).sum()) / (M * max(L, 1))
        A = eps * torch.eye(L, dtype=G.dtype, device=G.device)
        for i in chosen:
            A = A + G[i].T @ G[i]
        taken = torch.zeros(M, dtype=torch.bool, device=G.device)
        taken[chosen] = True
        eye_m = torch.eye(G.shape[-2], dtype=G.dtype, device=G.device)
        while len(chosen) < k:
            Ainv = torch.linalg.inv(A)
            # det(A + G_iᵀG_i) = det(A) det(I + G_i A⁻¹ G_iᵀ): score all candidates at once
            gain = torch.logdet(eye_m + G @ Ainv @ G.transpose(-1, -2))
            gain = torch.where(taken, torch.full_like(gain, -math.inf), gain)
            best = int(torch.argmax(gain))
            chosen.append(best)
            taken[best] = True
            A = A + G[best].T @ G[best]
    return torch.tensor(chosen[:k], dtype=torch.long, device=candidates.device)

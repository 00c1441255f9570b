"""``calibrate`` / ``calibrate_batch``: the kinematic calibration workflow of §2.11 and its result."""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor

from ..chain import DHChain
from ..errors import ConventionError, ShapeError
from .identifiability import IdentifiabilityReport, model_reports
from .model import CalibrationModel, check_measurements, pose_residual
from .solvers import gradient_descent, least_squares

__all__ = ["CalibrationResult", "calibrate", "calibrate_batch", "validation_error", "METHODS"]

METHODS = ("least_squares", "gradient")


def validation_error(chain: DHChain, q: Tensor, T: Tensor) -> dict[str, float | None]:
    """Pose error of ``chain`` against measurements: ``q (N, n)``, ``T (N, 4, 4)`` or positions ``(N, 3)``.

    Returns ``position_rms``, ``position_max`` (metres) and ``orientation_rms``, ``orientation_max`` (radians,
    angle of R_m Rᵀ; None for position-only data).
    """
    position_only = check_measurements(q, T, chain.n_joints, chain.dtype)
    with torch.no_grad():
        res = pose_residual(chain.forward_kinematics(q), T, 1.0)
    pos = res[..., :3].norm(dim=-1)
    out = {
        "position_rms": float(pos.square().mean().sqrt()),
        "position_max": float(pos.max()),
        "orientation_rms": None,
        "orientation_max": None,
    }
    if not position_only:
        ang = res[..., 3:].norm(dim=-1)
        out.update(orientation_rms=float(ang.square().mean().sqrt()), orientation_max=float(ang.max()))
    return out


@dataclass
class CalibrationResult:
    """Outcome of one calibration.

    ``chain``: the calibrated copy; ``nominal_chain``: a copy of the nominal one. ``residuals``: position RMS
    (metres) at ζ_n and after every iteration; ``orientation_residuals``: the same in radians (None for
    position-only data). ``names``/``nominal``/``identified``: the candidate parameters (metres / radians;
    base and tool entries are the pose corrections Δ). ``report``: identifiability at the nominal parameters.
    """

    chain: DHChain
    nominal_chain: DHChain
    method: str
    names: list[str]
    units: list[str]
    nominal: Tensor
    identified: Tensor
    report: IdentifiabilityReport
    residuals: list[float]
    orientation_residuals: list[float] | None
    iterations: int
    converged: bool
    q: Tensor = field(repr=False)
    measured: Tensor = field(repr=False)

    @property
    def position_only(self) -> bool:
        return self.measured.shape[-1] == 3 and self.measured.ndim == self.q.ndim

    def parameter_table(self) -> list[dict]:
        """Rows ``{name, nominal, identified, delta, unit, identifiable}`` for every candidate parameter."""
        fixed = set(self.report.unidentifiable)
        rows = []
        for name, unit, nom, idf in zip(
            self.names, self.units, self.nominal.tolist(), self.identified.tolist()
        ):
            rows.append(
                {
                    "name": name,
                    "nominal": nom,
                    "identified": idf,
                    "delta": idf - nom,
                    "unit": unit,
                    "identifiable": name not in fixed,
                }
            )
        return rows

    def to_markdown(self) -> str:
        """The parameter table as Markdown (lengths in mm, angles in degrees)."""
        lines = ["| parameter | nominal | identified | delta | |", "|---|---:|---:|---:|---|"]
        for r in self.parameter_table():
            f, u = (1e3, "mm") if r["unit"] == "m" else (57.29577951308232, "deg")
            note = "" if r["identifiable"] else "fixed (unidentifiable)"
            lines.append(
                f"| {r['name']} | {r['nominal'] * f:.4f} | {r['identified'] * f:.4f} | "
                f"{r['delta'] * f:+.4f} {u} | {note} |"
            )
        return "\n".join(lines)

    def validation_error(self, q: Tensor, T: Tensor) -> dict[str, float | None]:
        """:func:`validation_error` of the calibrated chain."""
        return validation_error(self.chain, q, T)

    def plot_residuals(self, path: str | Path, q: Tensor | None = None, T: Tensor | None = None) -> Path:
        """PNG: per-pose position errors before/after (histogram), orientation likewise, RMS per iteration.

        Uses the calibration data, or ``q``/``T`` (e.g. held-out poses) when given. Needs matplotlib; draws on
        a :class:`matplotlib.figure.Figure` (no pyplot, the process's backend is left alone).
        """
        from matplotlib.figure import Figure

        q = self.q if q is None else q
        T = self.measured if T is None else T
        with torch.no_grad():
            before = pose_residual(self.nominal_chain.forward_kinematics(q), T, 1.0)
            after = pose_residual(self.chain.forward_kinematics(q), T, 1.0)
        panels = 2 if before.shape[-1] == 3 else 3
        fig = Figure(figsize=(5 * panels, 4))
        axes = fig.subplots(1, panels)
        for ax, sl, f, unit in (
            (axes[0], slice(0, 3), 1e3, "mm"),
            (axes[-1], slice(3, 6), 57.29577951308232, "deg"),
        )[: panels - 1]:
            b, a = (x[..., sl].norm(dim=-1).cpu().numpy() * f for x in (before, after))
            lo, hi = max(min(b.min(), a.min()), 1e-9 * f), max(b.max(), a.max(), 2e-9 * f)
            bins = [lo * (hi / lo) ** (i / 50) for i in range(51)]  # log bins: errors span decades
            ax.hist(b.clip(lo, hi), bins=bins, alpha=0.6, label="nominal")
            ax.hist(a.clip(lo, hi), bins=bins, alpha=0.6, label="calibrated")
            ax.set_xscale("log")
            ax.set_xlabel(f"{'position' if sl.start == 0 else 'orientation'} error per pose [{unit}]")
            ax.set_ylabel("poses")
            ax.legend()
        ax = axes[1] if panels == 3 else axes[-1]
        ax.semilogy([r * 1e3 for r in self.residuals], marker="o", ms=3, label="position RMS [mm]")
        if self.orientation_residuals is not None:
            ax.semilogy(
                [r * 57.29577951308232 for r in self.orientation_residuals],
                marker="s",
                ms=3,
                label="orientation RMS [deg]",
            )
        ax.set_xlabel(f"iteration ({self.method})")
        ax.set_title("calibration poses", fontsize=10)
        ax.legend()
        fig.suptitle(f"calibration of '{self.chain.name}'")
        fig.tight_layout()
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(path, dpi=110)
        return path

    def summary(self) -> str:
        lines = [
            f"calibration of '{self.chain.name}' ({self.method}): {self.iterations} iterations, "
            f"{'converged' if self.converged else 'NOT converged'}",
            f"position RMS {self.residuals[0] * 1e3:.4f} mm -> {self.residuals[-1] * 1e3:.4f} mm",
        ]
        if self.orientation_residuals is not None:
            lines.append(
                f"orientation RMS {self.orientation_residuals[0] * 1e3:.4f} mrad -> "
                f"{self.orientation_residuals[-1] * 1e3:.4f} mrad"
            )
        return "\n".join(lines + [self.report.summary()])


def _run(
    model: CalibrationModel,
    q: Tensor,
    T: Tensor,
    position_only: bool,
    method: str,
    orientation_weight: float,
    rank_tol: float | None,
    solver_options: dict,
) -> list[CalibrationResult]:
    """Identifiability at ζ_n, then the solver, for ``q (K, N, n)``; one result per robot."""
    if method not in METHODS:
        raise ConventionError(f"unknown calibration method {method!r}; valid: {', '.join(METHODS)}")
    K = q.shape[0]
    zeta0 = model.nominal.expand(K, model.n_params).clone()
    reports, free = model_reports(model, zeta0, q, position_only, orientation_weight, rank_tol)
    solve = least_squares if method == "least_squares" else gradient_descent
    opts = {k: v for k, v in solver_options.items() if v is not None}
    out = solve(model, zeta0, free, q, T, orientation_weight=orientation_weight, **opts)
    cand = model.candidate.nonzero().flatten().tolist()
    length = model.is_length().tolist()
    names = [model.names[j] for j in cand]
    units = ["m" if length[j] else "rad" for j in cand]
    pos = torch.stack(out.position_rms, dim=-1).tolist()  # (K, iterations + 1)
    ori = None if out.orientation_rms is None else torch.stack(out.orientation_rms, dim=-1).tolist()
    chains = model.to_chains(out.zeta)
    nominal_copies = [c.copy() for c in model.chains]
    return [
        CalibrationResult(
            chain=chains[k],
            nominal_chain=nominal_copies[min(k, len(nominal_copies) - 1)],
            method=method,
            names=names,
            units=units,
            nominal=zeta0[k, cand].clone(),
            identified=out.zeta[k, cand].clone(),
            report=reports[k],
            residuals=pos[k],
            orientation_residuals=None if ori is None else ori[k],
            iterations=out.iterations,
            converged=bool(out.converged[k]),
            q=q[k],
            measured=T[k],
        )
        for k in range(K)
    ]


def calibrate_batch(
    chain: DHChain | Sequence[DHChain],
    q: Tensor,
    T: Tensor,
    method: str = "gradient",
    *,
    parameters: str | Iterable[str] = "all",
    base: bool = False,
    tool: bool = False,
    joint_offsets: bool = True,
    orientation_weight: float = 0.1,
    max_iterations: int | None = None,
    tol: float | None = None,
    rank_tol: float | None = None,
    progress: bool = True,
    **solver_options,
) -> list[CalibrationResult]:
    """Calibrate K robots in one call: ``q (K, N, n)``, ``T (K, N, 4, 4)`` or ``(K, N, 3)``.

    ``chain``: one shared nominal :class:`DHChain` or K of them (same structure). The parameter tensor is
    ``(K, P)`` and both methods run vectorised over K (one L-BFGS problem whose objective is the sum of
    the K independent losses). Options as in :func:`calibrate`.
    """
    model = CalibrationModel.from_chains(chain, parameters, base, tool, joint_offsets)
    if not isinstance(q, Tensor) or q.ndim != 3:
        shape = tuple(q.shape) if isinstance(q, Tensor) else type(q).__name__
        raise ShapeError(
            f"calibrate_batch expects q of shape (K, N, {model.n}), got {shape}; "
            "for one robot use calibrate()"
        )
    K = q.shape[0]
    if model.nominal.ndim == 2 and model.nominal.shape[0] != K:
        raise ShapeError(f"got {model.nominal.shape[0]} nominal chains for K = {K} robots in q")
    position_only = check_measurements(q, T, model.n, model.dtype, batch=(K,))
    opts = dict(max_iterations=max_iterations, tol=tol, progress=progress, **solver_options)
    return _run(model, q, T, position_only, method, orientation_weight, rank_tol, opts)


def calibrate(
    chain: DHChain,
    q: Tensor,
    T: Tensor,
    method: str = "least_squares",
    *,
    parameters: str | Iterable[str] = "all",
    base: bool = False,
    tool: bool = False,
    joint_offsets: bool = True,
    orientation_weight: float = 0.1,
    max_iterations: int | None = None,
    tol: float | None = None,
    rank_tol: float | None = None,
    progress: bool = True,
    **solver_options,
) -> CalibrationResult:
    """Identify the DH parameters of ``chain`` from joint readings ``q (N, n)`` and measured end-effector
    poses ``T (N, 4, 4)`` (or positions ``(N, 3)``), textbook §2.11. The nominal chain is left untouched.

    Args:
        method: ``"least_squares"`` — iterate (2.88)–(2.89) with the analytic calibration matrix Φ̄;
            ``"gradient"`` — minimise :func:`calibration_loss` with a torch optimiser
            (``optimizer="lbfgs"|"adam"``, ``loss="huber"|"soft_l1"|"l2"``, ``scale`` metres, ``lr``).
        parameters: ``"all"`` DH parameters, or kinds (``"a"``, ``"alpha"``, ``"d"``, ``"theta"``) / names
            (``"a2"``, ``"base_z"``) to estimate.
        base, tool: also estimate 6-parameter corrections of the base / tool frame.
        joint_offsets: include (True) or exclude (False) the encoder zero offsets (ϑ_i revolute,
            d_i prismatic).
        orientation_weight: metres per radian in the pose residual (default 0.1: 1 mrad ≙ 0.1 mm).
        max_iterations, tol: stopping rule (least squares: relative parameter change; gradient: relative loss
            change); ``rank_tol``: identifiability threshold (see :mod:`.identifiability`).
        progress: show a rich progress bar when stderr is a terminal.
        **solver_options: ``damping`` (least squares, default 1e-9); ``optimizer``, ``loss``, ``scale``
            (default 1e-3 m), ``lr``, ``precondition`` (``"gauss_newton"`` default, or ``"diagonal"``)
            for the gradient method.

    Parameters that the poses cannot identify are reported in ``result.report`` and kept at nominal.
    """
    model = CalibrationModel.from_chains(chain, parameters, base, tool, joint_offsets)
    if isinstance(q, Tensor) and q.ndim == 3:
        raise ShapeError(
            f"expected q of shape (N, {model.n}) for one robot, got {tuple(q.shape)}; "
            "use calibrate_batch for (K, N, n)"
        )
    position_only = check_measurements(q, T, model.n, model.dtype)
    opts = dict(max_iterations=max_iterations, tol=tol, progress=progress, **solver_options)
    return _run(model, q[None], T[None], position_only, method, orientation_weight, rank_tol, opts)[0]

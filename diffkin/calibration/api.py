"""``calibrate`` / ``calibrate_batch``: the kinematic calibration workflow of §2.11 and its result."""

from __future__ import annotations

import math
import warnings
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor

from ..chain import DHChain, KinematicChain
from ..errors import ConventionError, DiffkinError, OptionError, ShapeError, require
from ..validation import as_tensor, check_number, shape_str
from .error_models import build_model
from .identifiability import IdentifiabilityReport, model_reports
from .model import check_measurements, pose_residual
from .plausibility import MAX_CORRECTION, correction_findings, fit_failures
from .robust import outlier_rows, pose_errors, resolve_loss
from .solvers import gradient_descent, kfold_split, least_squares

__all__ = ["CalibrationResult", "calibrate", "calibrate_batch", "validation_error", "METHODS"]

METHODS = ("least_squares", "gradient")
_DEG = 180.0 / math.pi  # reports give lengths in mm and angles in degrees (console, parameters.md, summary)


def save_figure(fig, path: str | Path, tight: bool = True, **savefig) -> Path:
    """Lay out a matplotlib ``Figure`` (``tight``: ``tight_layout``, one extra draw) and write it to
    ``path`` (parent folders made; ``savefig``: more options of ``Figure.savefig``): every calibration
    result's residual plot."""
    if tight:
        fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110, **savefig)
    return path


def validation_error(chain: DHChain, q: Tensor, T: Tensor) -> dict[str, float | None]:
    """Pose error of ``chain`` against measurements: ``q (N, n)``, ``T (N, 4, 4)`` or positions ``(N, 3)``.

    Returns ``position_rms``, ``position_max`` (metres) and ``orientation_rms``, ``orientation_max`` (radians,
    angle of R_m Rᵀ; None for position-only data).
    """
    q, T, position_only = check_measurements(q, T, chain.n_joints, chain)
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
    ``converged``: the solver's stopping rule was met (not merely the iteration budget spent).
    ``success``: the result passed the plausibility checks of :mod:`.plausibility` (held-out error, noise
    ratio, size of the corrections); False with the reasons in ``failure`` (and a ``UserWarning``): the data
    are probably not of this robot, and the calibrated chain should not be used.
    ``chain`` is of the input's kind: a :class:`DHChain` (with a ``beta`` column for Hayati's model) or a
    :class:`~diffkin.models.urdf.URDFChain` (``to_urdf(path)`` writes it).
    """

    chain: KinematicChain
    nominal_chain: KinematicChain
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
    #: the error model used: "dh", "hayati" or "general" (what "auto" chose)
    error_model: str = "dh"
    #: fit residual over what ``measurement_noise`` explains (≈ 1 for an adequate model; None without noise)
    noise_ratio: float | None = None
    #: k-fold cross-validated held-out error: ``folds``, ``position_rms``/``position_max`` (m),
    #: ``orientation_rms`` (rad or None); None when not run (fewer than 2 poses per fold, or disabled)
    cross_validation: dict | None = None
    #: what the error model decided (e.g. which β replace which d)
    notes: list[str] = field(default_factory=list)
    #: the loss of the fit ("l2", "huber", "cauchy", "soft_l1"; :mod:`.robust`)
    loss: str = "l2"
    #: per-pose outlier report (:mod:`.robust`): the rows whose final residual norm exceeds
    #: ``outlier_threshold`` (metres), and every pose's final position (m) / orientation (rad) error
    outliers: list[int] = field(default_factory=list)
    outlier_threshold: float | None = None
    pose_position_errors: Tensor | None = field(default=None, repr=False)
    pose_orientation_errors: Tensor | None = field(default=None, repr=False)
    #: the plausibility checks (:mod:`.plausibility`) passed; else False and ``failure`` says why
    success: bool = True
    failure: str | None = None

    @property
    def determined(self) -> bool:
        """The poses determine every structurally identifiable parameter (``report.undetermined`` is empty);
        False: some are minimum-norm estimates and the error away from these poses can grow."""
        return not self.report.undetermined

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

    def display_rows(self) -> list[list[str]]:
        """The parameter table as text in the units every report uses (lengths mm, angles deg):
        ``[name, nominal, identified, delta, unit, note]`` per parameter (``to_markdown``, ``diffkin
        calibrate``'s table; :meth:`parameter_table` keeps metres and radians)."""
        rows = []
        for r in self.parameter_table():
            f, u = (1e3, "mm") if r["unit"] == "m" else (_DEG, "deg")
            rows.append([r["name"], f"{r['nominal'] * f:.4f}", f"{r['identified'] * f:.4f}",
                         f"{r['delta'] * f:+.4f}", u, "" if r["identifiable"] else "fixed (unidentifiable)"])
        return rows

    def to_markdown(self) -> str:
        """The parameter table as Markdown (lengths in mm, angles in degrees, as every report)."""
        lines = ["| parameter | nominal | identified | delta | |", "|---|---:|---:|---:|---|"]
        for name, nom, idf, delta, unit, note in self.display_rows():
            lines.append(f"| {name} | {nom} | {idf} | {delta} {unit} | {note} |")
        return "\n".join(lines)

    def validation_error(self, q: Tensor, T: Tensor) -> dict[str, float | None]:
        """:func:`validation_error` of the calibrated chain."""
        return validation_error(self.chain, q, T)

    def plot_residuals(self, path: str | Path, q: Tensor | None = None, T: Tensor | None = None) -> Path:
        """PNG: per-pose position errors before/after (histogram), orientation likewise, RMS per iteration.

        Uses the calibration data, or ``q``/``T`` (e.g. held-out poses) when given. Needs matplotlib; draws on
        a :class:`matplotlib.figure.Figure` (no pyplot, the process's backend is left alone).
        """
        Figure = require("matplotlib.figure", "plot", "CalibrationResult.plot_residuals").Figure

        if q is None and T is None:
            q, T = self.q, self.measured
        else:  # held-out poses: by the input rule, like the calibration data
            q, T, _ = check_measurements(self.q if q is None else q, self.measured if T is None else T,
                                         self.q.shape[-1], self.chain)
        with torch.no_grad():
            before = pose_residual(self.nominal_chain.forward_kinematics(q), T, 1.0)
            after = pose_residual(self.chain.forward_kinematics(q), T, 1.0)
        panels = 2 if before.shape[-1] == 3 else 3
        fig = Figure(figsize=(5 * panels, 4))
        axes = fig.subplots(1, panels)
        for ax, sl, f, unit in (
            (axes[0], slice(0, 3), 1e3, "mm"),
            (axes[-1], slice(3, 6), _DEG, "deg"),
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
                [r * _DEG for r in self.orientation_residuals],
                marker="s",
                ms=3,
                label="orientation RMS [deg]",
            )
        ax.set_xlabel(f"iteration ({self.method})")
        ax.set_ylabel("RMS error over the poses [mm | deg]" if self.orientation_residuals is not None
                      else "RMS position error [mm]")
        ax.set_title("calibration poses", fontsize=10)
        ax.legend()
        fig.suptitle(f"calibration of '{self.chain.name}'")
        return save_figure(fig, path)

    def outlier_summary(self) -> str:
        """One line: how many poses are beyond the outlier threshold (:mod:`.robust`), and which."""
        rows = ", ".join(map(str, self.outliers[:10])) + (", ..." if len(self.outliers) > 10 else "")
        return (f"outliers ({self.loss} loss): {len(self.outliers)} of {self.q.shape[0]} {self._noun} beyond "
                f"{self.outlier_threshold * 1e3:.4f} mm" + (f" (rows {rows})" if self.outliers else ""))

    #: what the summary calls the measurements and the fit's RMS (the contact result: contacts, distance)
    _noun, _quantity = "poses", "position"

    def _title(self) -> str:
        return f"calibration of '{self.chain.name}' ({self.method})"

    def _fit_lines(self) -> list[str]:
        """The summary's lines on the fit beyond the RMS: orientation and the cross-validated error."""
        lines = []
        if self.orientation_residuals is not None:
            lines.append(
                f"orientation RMS {self.orientation_residuals[0] * _DEG:.5f} deg -> "
                f"{self.orientation_residuals[-1] * _DEG:.5f} deg"
            )
        if self.cross_validation is not None:
            cv = self.cross_validation
            line = (f"{cv['folds']}-fold cross-validated held-out error: position RMS "
                    f"{cv['position_rms'] * 1e3:.4f} mm (max {cv['position_max'] * 1e3:.4f} mm)")
            if cv.get("orientation_rms") is not None:
                line += f", orientation RMS {cv['orientation_rms'] * _DEG:.5f} deg"
            lines.append(line)
        return lines

    def summary(self) -> str:
        lines = [
            f"{self._title()}: {self.iterations} iterations, "
            f"{'converged' if self.converged else 'NOT converged'}"
            + ("" if self.determined else f"; parameters NOT determined by these {self._noun} (below)")
            + ("" if self.success else f"; FAILED: {self.failure}"),
            f"{self._quantity} RMS {self.residuals[0] * 1e3:.4f} mm -> {self.residuals[-1] * 1e3:.4f} mm",
        ] + self._fit_lines()
        if self.noise_ratio is not None:
            excluded = self.loss != "l2" and 0 < len(self.outliers) < self.q.shape[0] / 2
            lines.append(f"fit residual / measurement noise: {self.noise_ratio:.2f} (about 1 expected"
                         + (", outliers excluded)" if excluded else ")"))
        if self.outlier_threshold is not None:
            lines.append(self.outlier_summary())
        lines += [f"note: {n}" for n in self.notes]
        return "\n".join(lines + [self.report.summary()])


def _check_options(method: str, orientation_weight, measurement_noise=None, max_correction=MAX_CORRECTION
                   ) -> None:
    """The calibration options that are numbers or names: refused with a typed error before any work."""
    if max_correction is not None:
        if not isinstance(max_correction, Sequence) or len(max_correction) != 2:
            raise OptionError("expected max_correction as (metres, radians) or None, got "
                              f"{max_correction!r}")
        check_number(max_correction[0], "max_correction[0]", unit=" (metres)")
        check_number(max_correction[1], "max_correction[1]", unit=" (radians)")
    if method not in METHODS:
        raise ConventionError(f"unknown calibration method {method!r}; valid: {', '.join(METHODS)}")
    check_number(orientation_weight, "orientation_weight", positive=False, unit=" (metres per radian)")
    if measurement_noise is not None:
        if not isinstance(measurement_noise, Sequence) or not 1 <= len(measurement_noise) <= 2:
            raise DiffkinError("expected measurement_noise as (sigma_position [m], sigma_orientation "
                               f"[rad]), got {measurement_noise!r}")
        for name, v in zip(("measurement_noise[0]", "measurement_noise[1]"), measurement_noise):
            check_number(v, name)


def _solve(model, q, T, position_only, method, orientation_weight, rank_tol, solver_options):
    """Identifiability at ζ_n, then the solver, for ``q (K, N, n)``: ``(output, reports, ζ_n (K, P))``."""
    K = q.shape[0]
    zeta0 = model.nominal.expand(K, model.n_params).clone()
    reports, free = model_reports(model, zeta0, q, position_only, orientation_weight, rank_tol)
    solve = least_squares if method == "least_squares" else gradient_descent
    opts = {k: v for k, v in solver_options.items() if v is not None}
    out = solve(model, zeta0, free, q, T, orientation_weight=orientation_weight, **opts)
    return out, reports, zeta0


def _noise_ratio(model, zeta, q, T, position_only, rank, noise) -> tuple[float, str]:
    """χ = √(Σ (r/σ)² / (rows − rank)) of the final fit (≈ 1 when the noise explains the residual)."""
    sp, so = float(noise[0]), float(noise[1]) if len(noise) > 1 else 0.0
    with torch.no_grad():
        r = model.residual(zeta[None], q[None], T[None], 1.0)[0]
    chi2 = (r[..., :3] / sp).square().sum()
    rows = r[..., :3].numel()
    detail = f"position RMS {float(r[..., :3].norm(dim=-1).square().mean().sqrt()) * 1e3:.4f} mm vs " \
             f"{math.sqrt(3) * sp * 1e3:.4f} mm expected"
    if not position_only and so > 0:
        chi2 = chi2 + (r[..., 3:] / so).square().sum()
        rows += r[..., 3:].numel()
        detail += f", orientation RMS {float(r[..., 3:].norm(dim=-1).square().mean().sqrt()) * _DEG:.5f} " \
                  f"deg vs {math.sqrt(3) * so * _DEG:.5f} deg expected"
    return math.sqrt(float(chi2) / max(rows - rank, 1)), detail


def _cross_validate(model, q, T, position_only, method, w, rank_tol, opts, folds: int) -> dict | None:
    """k-fold held-out error of one robot's data ``q (N, n)``: the k fits run as one batch."""
    split = kfold_split(q.shape[0], folds, q.device)
    if split is None:
        return None
    train, test = split
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        out, _, _ = _solve(model, q[train], T[train], position_only, method, w, rank_tol,
                           dict(opts, progress=False))
    with torch.no_grad():
        r = model.residual(out.zeta, q[test], T[test], 1.0)
    pos = r[..., :3].norm(dim=-1)
    res = {"folds": folds, "position_rms": float(pos.square().mean().sqrt()),
           "position_max": float(pos.max()), "orientation_rms": None}
    if not position_only:
        res["orientation_rms"] = float(r[..., 3:].norm(dim=-1).square().mean().sqrt())
    return res


def _undetermined_note(report: IdentifiabilityReport, n_poses: int) -> str:
    """What degenerate data (too few or too similar poses) leave open, for ``notes`` and the warning."""
    poses = "this pose determines" if n_poses == 1 else f"these {n_poses} poses determine"
    return (f"{poses} only {report.rank} of {report.structural_rank} identifiable "
            f"parameters; {len(report.undetermined)} ({', '.join(report.undetermined[:4])}"
            f"{', ...' if len(report.undetermined) > 4 else ''}) are minimum-norm estimates, so the error "
            f"away from these poses can grow: add at least {report.more_poses_needed} well-spread poses")


def _run(
    model,
    q: Tensor,
    T: Tensor,
    position_only: bool,
    method: str,
    orientation_weight: float,
    rank_tol: float | None,
    solver_options: dict,
    kind: str = "dh",
    measurement_noise=None,
    cross_validation: int | None = None,
    max_correction: tuple[float, float] | None = MAX_CORRECTION,
) -> list[CalibrationResult]:
    """Identifiability at ζ_n, then the solver, for ``q (K, N, n)``; one result per robot."""
    out, reports, zeta0 = _solve(model, q, T, position_only, method, orientation_weight, rank_tol,
                                 solver_options)
    K = q.shape[0]
    cand = model.candidate.nonzero().flatten().tolist()
    length = model.is_length().tolist()
    names = [model.names[j] for j in cand]
    units = ["m" if length[j] else "rad" for j in cand]
    pos = torch.stack(out.position_rms, dim=-1).tolist()  # (K, iterations + 1)
    ori = None if out.orientation_rms is None else torch.stack(out.orientation_rms, dim=-1).tolist()
    chains = model.to_chains(out.zeta)
    nominal_copies = [c.copy() for c in model.chains]
    results = []
    loss = solver_options.get("loss", "l2")
    for k in range(K):
        pos_err, ori_err, norms = pose_errors(model, out.zeta[k], q[k], T[k], orientation_weight)
        outliers, threshold = outlier_rows(norms, measurement_noise, orientation_weight, position_only)
        # a robust fit's χ is that of its inliers, while they are the majority (else the model, not a few
        # poses, fails: every pose counts and the warning below says so)
        robust = loss != "l2" and 0 < len(outliers) < norms.numel() / 2
        keep = norms <= threshold if robust else slice(None)
        ratio = None
        if measurement_noise is not None:
            ratio, detail = _noise_ratio(model, out.zeta[k], q[k][keep], T[k][keep], position_only,
                                         reports[k].rank, measurement_noise)
            if ratio > 2.0:
                warnings.warn(
                    f"calibration of '{chains[k].name}' (error model {kind!r}): the fit residual is "
                    f"{ratio:.1f}x what the measurement noise explains ({detail}). Likely causes: an error "
                    "model that cannot represent the robot (e.g. 'dh' with parallel axes: use 'hayati' or "
                    "'general'), outliers in the measurements, wrong joint readings (units, order, timing) "
                    "or a wrong noise level.",
                    UserWarning,
                    stacklevel=3,
                )
        notes = list(getattr(model, "notes", []))
        if reports[k].undetermined:
            notes.append(_undetermined_note(reports[k], q.shape[1]))
            which = f"'{chains[k].name}'" + (f" (robot {k} of the batch)" if K > 1 else "")
            warnings.warn(f"calibration of {which}: {notes[-1]}", UserWarning, stacklevel=3)
        cv = None
        if cross_validation:
            cv = _cross_validate(model, q[k], T[k], position_only, method, orientation_weight, rank_tol,
                                 solver_options, int(cross_validation))
        nominal_k = nominal_copies[min(k, len(nominal_copies) - 1)]
        failures = fit_failures(pos[k][-1], None if ori is None else ori[k][-1], cv, ratio, measurement_noise)
        wrong, end = correction_findings(nominal_k, chains[k], q[k], max_correction)
        failures += wrong
        which = f"'{chains[k].name}'" + (f" (robot {k} of the batch)" if K > 1 else "")
        if end is not None:
            notes.append(end)
            warnings.warn(f"calibration of {which}: {end}", UserWarning, stacklevel=3)
        failure = "; ".join(failures) or None
        if failure is not None:
            warnings.warn(f"calibration of {which} FAILED (result.success is False): {failure}", UserWarning,
                          stacklevel=3)
        results.append(
            CalibrationResult(
                chain=chains[k],
                nominal_chain=nominal_k,
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
                error_model=kind,
                noise_ratio=ratio,
                cross_validation=cv,
                notes=notes,
                loss=loss,
                outliers=outliers,
                outlier_threshold=threshold,
                pose_position_errors=pos_err,
                pose_orientation_errors=ori_err,
                success=failure is None,
                failure=failure,
            )
        )
    return results


def calibrate_batch(
    chain: KinematicChain | Sequence[KinematicChain],
    q: Tensor,
    T: Tensor,
    method: str = "gradient",
    *,
    error_model: str = "auto",
    measurement_noise: tuple[float, float] | None = None,
    loss: str | None = None,
    parameters: str | Iterable[str] = "all",
    base: bool = False,
    tool: bool = False,
    joint_offsets: bool = True,
    orientation_weight: float = 0.1,
    max_iterations: int | None = None,
    tol: float | None = None,
    rank_tol: float | None = None,
    progress: bool = True,
    max_correction: tuple[float, float] | None = MAX_CORRECTION,
    **solver_options,
) -> list[CalibrationResult]:
    """Calibrate K robots in one call: ``q (K, N, n)``, ``T (K, N, 4, 4)`` or ``(K, N, 3)``.

    ``chain``: one shared nominal chain (DHChain or URDFChain) or K of them (same structure). The parameter
    tensor is ``(K, P)`` and both methods run vectorised over K (one L-BFGS problem whose objective is the sum
    of the K independent losses). Options as in :func:`calibrate`.
    """
    _check_options(method, orientation_weight, measurement_noise, max_correction)
    model, kind = build_model(chain, error_model, parameters, base, tool, joint_offsets)
    ref = model.chains[0]
    q = as_tensor(q, "q", dtype=ref.dtype, device=ref.device) if q is not None else q
    if q is None or q.ndim != 3:
        shape = shape_str(q.shape) if q is not None else "None"
        raise ShapeError(
            f"calibrate_batch expects q of shape (K, N, {model.n}), got {shape}; "
            "for one robot use calibrate()"
        )
    K = q.shape[0]
    if model.nominal.ndim == 2 and model.nominal.shape[0] != K:
        raise ShapeError(f"got {model.nominal.shape[0]} nominal chains for K = {K} robots in q")
    if K == 0:  # no robots: validate what there is, no result
        T = as_tensor(T, "T", dtype=ref.dtype, device=ref.device)
        if T.ndim == 0 or T.shape[0] != 0:
            raise ShapeError(f"q holds K = 0 robots but T has shape {shape_str(T.shape)}")
        return []
    q, T, position_only = check_measurements(q, T, model.n, ref, batch=(K,))
    loss, scale = resolve_loss(method, loss, solver_options.pop("scale", None), measurement_noise,
                               orientation_weight, position_only)
    opts = dict(max_iterations=max_iterations, tol=tol, progress=progress, loss=loss, scale=scale,
                **solver_options)
    return _run(model, q, T, position_only, method, orientation_weight, rank_tol, opts, kind,
                measurement_noise, max_correction=max_correction)


def calibrate(
    chain: KinematicChain,
    q: Tensor,
    T: Tensor,
    method: str = "least_squares",
    *,
    error_model: str = "auto",
    measurement_noise: tuple[float, float] | None = None,
    loss: str | None = None,
    cross_validation: int | None = 5,
    parameters: str | Iterable[str] = "all",
    base: bool = False,
    tool: bool = False,
    joint_offsets: bool = True,
    orientation_weight: float = 0.1,
    max_iterations: int | None = None,
    tol: float | None = None,
    rank_tol: float | None = None,
    progress: bool = True,
    max_correction: tuple[float, float] | None = MAX_CORRECTION,
    **solver_options,
) -> CalibrationResult:
    """Identify the geometry of ``chain`` from joint readings ``q (N, n)`` and measured end-effector
    poses ``T (N, 4, 4)`` (or positions ``(N, 3)``), textbook §2.11. The nominal chain is left untouched.

    Measured rotation blocks off orthonormal by up to 1e-3 are accepted and re-orthonormalised (the one rule
    of :data:`diffkin.transforms.RIGIDITY_TOLERANCE`); worse ones are refused with the deviation and index.

    Args:
        error_model: what is estimated (:mod:`.error_models`): ``"dh"`` the DH table (a, α, d, ϑ);
            ``"hayati"`` the same with Hayati's β_i in place of d_i for near-parallel consecutive axes
            (result: a DHChain with a ``beta`` column); ``"general"`` six origin coordinates per joint of a
            URDF chain, redundancy removed by the identifiability analysis (result: a URDFChain,
            ``result.chain.to_urdf(path)``); ``"auto"`` (default): ``"general"`` for URDF chains, ``"hayati"``
            for DH chains with near-parallel consecutive axes, ``"dh"`` otherwise.
        measurement_noise: ``(σ_position [m], σ_orientation [rad])``, the standard deviation of each
            coordinate of the measured position and rotation vector. The fit residual is compared with what
            this noise explains (``result.noise_ratio``, χ = √(Σ(r/σ)²/(rows − rank)) ≈ 1); above 2 a
            ``UserWarning`` names the likely causes.
        loss: ``"huber"`` or ``"cauchy"`` for measurements with outliers (a mis-read target, a bumped
            reflector), ``"soft_l1"``, or ``"l2"`` (plain least squares); None: ``"l2"`` for least squares,
            ``"huber"`` for the gradient method. Quadratic up to a scale of 2 √(3σ_p² + 3(w σ_o)²) from
            ``measurement_noise`` (else 1 mm, or ``scale=`` metres); least squares then iterates reweighted
            least squares (:mod:`.robust`). Either way the result reports the poses whose final residual
            exceeds 3x the noise's expected norm (``result.outliers``, ``result.pose_position_errors``).
        cross_validation: k of the k-fold cross-validated held-out error in ``result.cross_validation``
            (default 5; run when there are at least 4k poses; 0/None: off). The k fits run as one batch.
        method: ``"least_squares"`` — iterate (2.88)–(2.89) with the calibration matrix Φ̄;
            ``"gradient"`` — minimise :func:`calibration_loss` with a torch optimiser
            (``optimizer="lbfgs"|"adam"``, ``lr``; ``loss`` and ``scale`` as above).
        parameters: ``"all"`` DH parameters, or kinds (``"a"``, ``"alpha"``, ``"d"``, ``"theta"``) / names
            (``"a2"``, ``"base_z"``) to estimate.
        base, tool: also estimate 6-parameter corrections of the base / tool frame.
        joint_offsets: include (True) or exclude (False) the encoder zero offsets (ϑ_i revolute,
            d_i prismatic).
        orientation_weight: metres per radian in the pose residual (default 0.1: 1 mrad ≙ 0.1 mm).
        max_iterations, tol: stopping rule (least squares: relative parameter change; gradient: relative loss
            change); ``rank_tol``: identifiability threshold (see :mod:`.identifiability`).
        progress: show a rich progress bar when stderr is a terminal.
        max_correction: ``(metres, radians)``, the plausibility bound of one link's correction (default
            5 cm / 10°; None: not checked). A link before the last moved by more fails the result (the data
            are of another robot); the end link (last link, tail, tool) warns and names the URDF link that
            would fit (:mod:`.plausibility`).
        **solver_options: ``damping`` (least squares: λ added to the normal matrix's diagonal on unit-norm
            columns, (3.59); default 1e-14 in float64, 1e-6 in float32); ``scale`` (metres, the robust loss's;
            default from ``measurement_noise``, else 1e-3 m); ``optimizer``, ``lr``,
            ``precondition`` (``"gauss_newton"`` default, or ``"diagonal"``)
            for the gradient method.

    Parameters that no pose set can identify (the model's redundancies) are reported in ``result.report``
    with the reason and kept at nominal; those only these poses leave undetermined (few poses) are estimated
    in the span the poses determine (minimum-norm update) and listed in ``result.report.undetermined``.

    ``result.success`` is False, with the reasons in ``result.failure`` and a ``UserWarning``, when the
    result is not credible (:mod:`.plausibility`): a cross-validated held-out error more than 5x the fit's, a
    fit residual more than 5x what ``measurement_noise`` explains, or a link before the last corrected by
    more than ``max_correction``. ``diffkin calibrate`` then exits with status 2 and does not write the robot
    unless ``--force``.
    """
    _check_options(method, orientation_weight, measurement_noise, max_correction)
    model, kind = build_model(chain, error_model, parameters, base, tool, joint_offsets)
    ref = model.chains[0]
    q = as_tensor(q, "q", dtype=ref.dtype, device=ref.device) if q is not None else q
    if q is not None and q.ndim == 3:
        raise ShapeError(
            f"expected q of shape (N, {model.n}) for one robot, got {shape_str(q.shape)}; "
            "use calibrate_batch for (K, N, n)"
        )
    q, T, position_only = check_measurements(q, T, model.n, ref)
    loss, scale = resolve_loss(method, loss, solver_options.pop("scale", None), measurement_noise,
                               orientation_weight, position_only)
    opts = dict(max_iterations=max_iterations, tol=tol, progress=progress, loss=loss, scale=scale,
                **solver_options)
    folds = cross_validation if cross_validation and q.shape[0] >= 4 * cross_validation else None
    return _run(model, q[None], T[None], position_only, method, orientation_weight, rank_tol, opts, kind,
                measurement_noise, folds, max_correction)[0]

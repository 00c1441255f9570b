"""``calibrate_contacts``: the robot's geometry from a probe tip touching fixed spheres or planes (§2.11 with
distance residuals; model in :mod:`.contact_model`), and its result."""

from __future__ import annotations

import math
import warnings
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor

from ..chain import KinematicChain
from ..errors import ConventionError, DiffkinError, OptionError, ShapeError, require
from ..validation import as_tensor, check_number, shape_str, tensors
from .api import CalibrationResult, _check_options, _undetermined_note, save_figure
from .contact_model import (
    SURFACES,
    ContactModel,
    contact_reports,
    fit_fixtures,
    signed_distance,
    tip_positions,
)
from .error_models import build_model
from .plausibility import MAX_CORRECTION, correction_findings, fit_failures
from .robust import resolve_loss
from .solvers import fold_fits, gradient_descent, least_squares

__all__ = ["ContactCalibrationResult", "calibrate_contacts"]

_MEDIAN_TO_SIGMA = 1.4826  # σ / median |r| of one Gaussian coordinate


@dataclass
class ContactCalibrationResult(CalibrationResult):
    """Outcome of :func:`calibrate_contacts`: a :class:`CalibrationResult` whose residuals are the signed
    distances of the tip to its fixture (metres; ``residuals``: their RMS at the start and per iteration,
    ``pose_position_errors``: |distance| per posture; ``orientation_residuals`` None), with

    ``surface``: ``"sphere"`` or ``"plane"``; ``fixtures`` ``(F, 4)``: per fixture the sphere's centre and
    radius [cx, cy, cz, r] or the plane [nx, ny, nz, d] (nᵀp = d, n unit) in the base frame, fitted (a known
    radius stays as given); ``initial_fixtures``: those fitted to the nominal robot's tips;
    ``fixture`` ``(N,)``: the fixture of each posture; ``tip`` ``(3,)``: the tip in the end frame;
    ``cross_validation``: ``folds``, ``distance_rms``, ``distance_max`` (m) of held-out postures.
    """

    surface: str = "sphere"
    fixtures: Tensor | None = None
    initial_fixtures: Tensor | None = field(default=None, repr=False)
    fixture: Tensor | None = field(default=None, repr=False)
    tip: Tensor | None = field(default=None, repr=False)

    @property
    def position_only(self) -> bool:
        return False

    def distances(self, q: Tensor, fixture=None, *, nominal: bool = False) -> Tensor:
        """Signed distances ``(N,)`` (m) of the calibrated (``nominal``: the nominal) robot's tip at ``q
        (N, n)`` to the fitted (nominal: the initial) fixtures; ``fixture (N,)`` default all 0."""
        chain = self.nominal_chain if nominal else self.chain
        fix = self.initial_fixtures if nominal else self.fixtures
        q, onehot = _postures(chain, q, fixture, fix.shape[0])
        with torch.no_grad():
            return signed_distance(tip_positions(chain, q, self.tip), onehot @ fix, self.surface)

    def validation_error(self, q: Tensor, fixture=None) -> dict[str, float | None]:
        """Held-out contacts ``q (N, n)`` (on fixtures ``fixture (N,)``): ``distance_rms``, ``distance_max``
        (m) of the calibrated robot to the fitted fixtures."""
        d = self.distances(q, fixture)
        return {"distance_rms": float(d.square().mean().sqrt()), "distance_max": float(d.abs().max())}

    def plot_residuals(self, path: str | Path, q: Tensor | None = None, fixture=None) -> Path:
        """PNG: per-posture |distance| before (nominal robot, initial fixtures) and after (histogram), and
        the RMS per iteration; of the calibration postures or ``q``/``fixture``. Needs matplotlib (a Figure,
        no pyplot)."""
        Figure = require("matplotlib.figure", "plot", "ContactCalibrationResult.plot_residuals").Figure
        if q is None:
            q, fixture = self.q, self.fixture
        b = self.distances(q, fixture, nominal=True).abs().cpu().numpy() * 1e3
        a = self.distances(q, fixture).abs().cpu().numpy() * 1e3
        fig = Figure(figsize=(10, 4))
        ax, ax2 = fig.subplots(1, 2)
        lo, hi = max(min(b.min(), a.min()), 1e-9), max(b.max(), a.max(), 2e-9)
        bins = [lo * (hi / lo) ** (i / 40) for i in range(41)]
        ax.hist(b.clip(lo, hi), bins=bins, alpha=0.6, label="nominal")
        ax.hist(a.clip(lo, hi), bins=bins, alpha=0.6, label="calibrated")
        ax.set_xscale("log")
        ax.set_xlabel(f"|distance| of the tip to its {self.surface} per posture [mm]")
        ax.set_ylabel("postures")
        ax.legend()
        ax2.semilogy([r * 1e3 for r in self.residuals], marker="o", ms=3)
        ax2.set_xlabel(f"iteration ({self.method})")
        ax2.set_ylabel("distance RMS [mm]")
        fig.suptitle(f"contact calibration of '{self.chain.name}' ({self.surface})")
        return save_figure(fig, path)

    _noun, _quantity = "contacts", "distance"

    def _title(self) -> str:
        return f"contact calibration of '{self.chain.name}' ({self.surface}, {self.method})"

    def _fit_lines(self) -> list[str]:
        """The fitted fixtures and the cross-validated distance."""
        lines = []
        for f, v in enumerate(self.fixtures.tolist()):
            if self.surface == "sphere":
                lines.append(f"sphere {f}: centre [{v[0] * 1e3:.3f}, {v[1] * 1e3:.3f}, {v[2] * 1e3:.3f}] mm, "
                             f"radius {v[3] * 1e3:.4f} mm")
            else:
                lines.append(f"plane {f}: normal [{v[0]:.6f}, {v[1]:.6f}, {v[2]:.6f}], offset "
                             f"{v[3] * 1e3:.4f} mm")
        if self.cross_validation is not None:
            cv = self.cross_validation
            lines.append(f"{cv['folds']}-fold cross-validated held-out distance RMS "
                         f"{cv['distance_rms'] * 1e3:.4f} mm (max {cv['distance_max'] * 1e3:.4f} mm)")
        return lines


def _postures(chain, q, fixture, F: int) -> tuple[Tensor, Tensor]:
    """Validated ``(q (N, n), one-hot (N, F))`` in the chain's dtype and device."""
    (q,) = tensors(("q", q, (chain.n_joints,)), like=chain)
    if q.ndim != 2 or q.shape[0] < 1:
        raise ShapeError(f"expected q of shape (N, {chain.n_joints}), got {shape_str(q.shape)}")
    N = q.shape[0]
    if fixture is None:
        fixture = torch.zeros(N, dtype=torch.long, device=q.device)
    fixture = torch.as_tensor(fixture, device=q.device)
    if fixture.dtype.is_floating_point or fixture.dtype == torch.bool or fixture.is_complex():
        raise DiffkinError(f"expected fixture as integer indices (N,), got dtype {fixture.dtype}")
    if fixture.shape != (N,):
        raise ShapeError(f"expected fixture of shape (N,) = ({N},), one index per posture, got "
                         f"{shape_str(fixture.shape)}")
    if N and (int(fixture.min()) < 0 or int(fixture.max()) >= F):
        raise ShapeError(f"fixture indices must lie in 0..{F - 1}, got {int(fixture.min())}.."
                         f"{int(fixture.max())}")
    return q, torch.nn.functional.one_hot(fixture.long(), F).to(q)


def calibrate_contacts(
    chain: KinematicChain,
    q: Tensor,
    surface: str = "sphere",
    *,
    fixture: Tensor | None = None,
    radius=None,
    tip: Tensor | None = None,
    method: str = "least_squares",
    error_model: str = "auto",
    measurement_noise: float | None = None,
    loss: str | None = None,
    cross_validation: int | None = 5,
    parameters: str | Iterable[str] = "all",
    base: bool = False,
    tool: bool = False,
    joint_offsets: bool = True,
    max_iterations: int | None = None,
    tol: float | None = None,
    rank_tol: float | None = None,
    progress: bool = True,
    max_correction: tuple[float, float] | None = MAX_CORRECTION,
    **solver_options,
) -> ContactCalibrationResult:
    """Identify the geometry of ``chain`` from joint readings ``q (N, n)`` taken with its tip touching fixed
    spheres or planes (a touch probe, a ball in a socket): one zero distance per posture, the fixtures'
    unknown geometry estimated with the robot's (textbook §2.11 with the distance residuals of
    :mod:`.contact_model`). The nominal chain is left untouched.

    Args:
        chain: the nominal robot (DHChain, URDFChain or MJCFChain).
        q: joint readings ``(N, n)``, one per contact.
        surface: ``"sphere"`` (the tip's centre at a fixed distance from a fixed point: a ball probe on a
            reference sphere has radius R + ρ; a tip in a kinematic socket, a sphere about the socket's
            centre) or ``"plane"`` (a flat surface; the probe's ball radius is absorbed by the offset).
        fixture: ``(N,)`` integer index of the fixture each posture touches (default all 0): several
            spheres or planes, each with its own unknown geometry.
        radius: the spheres' known radii (metres; a number or one per fixture); None: estimated. Contact
            distances have no length scale of their own: with unknown radii (and with planes) the scale of
            the robot is unidentifiable — one length is reported and kept nominal.
        tip: the tip in the chain's end frame ``(3,)`` (metres; default the end frame's origin).
        method, error_model, loss, cross_validation, parameters: as :func:`calibrate` (losses and scale in
            metres of distance; ``cross_validation`` needs 4k contacts).
        base, tool, joint_offsets, max_iterations, tol, rank_tol: as :func:`calibrate`.
        progress, max_correction, solver_options: as :func:`calibrate`.
        measurement_noise: σ (metres), the standard deviation of the probe's trigger distance:
            ``result.noise_ratio`` χ = √(Σ (d/σ)² / (N − rank)) ≈ 1 for an adequate model (a
            ``UserWarning`` above 2), the outlier threshold 3σ (else 3 × 1.48 × the median |d|) and the
            robust loss's default scale 2σ.

    Returns:
        :class:`ContactCalibrationResult` (a :class:`CalibrationResult`): the calibrated ``chain``, the
        fitted ``fixtures``, the identifiability report (what contacts cannot separate from the fixtures'
        geometry — e.g. the base's pose about a sphere's centre, its shift along a plane, the scale without
        a known radius — fixed at nominal and named with the dependency), cross-validation, noise ratio,
        outliers and ``success`` by the plausibility checks of :func:`calibrate`.

    Raises:
        ShapeError, DTypeError, NonFiniteError, DiffkinError: joint readings of another robot, NaN readings,
            fixture indices of another shape or range, non-positive radii, a fixture touched in too few
            postures (a sphere needs 4 with an unknown radius, a plane 3) or in degenerate ones.
        ConventionError, OptionError: unknown ``surface``, ``method`` or ``loss``; ``radius`` for planes.
    """
    if surface not in SURFACES:
        raise ConventionError(f"unknown surface {surface!r}; valid: {', '.join(SURFACES)}")
    _check_options(method, 0.1, None, max_correction)
    if surface == "plane" and radius is not None:
        raise OptionError("radius is for spheres; a plane has none (the probe's ball radius is absorbed by "
                          "the plane's offset)")
    sigma = None if measurement_noise is None else check_number(measurement_noise, "measurement_noise",
                                                                unit=" (metres)")
    robot, kind = build_model(chain, error_model, parameters, base, tool, joint_offsets)
    ref = robot.chains[0]
    q = as_tensor(q, "q", dtype=ref.dtype, device=ref.device) if q is not None else q
    if q is None or q.ndim != 2 or q.shape[-1] != robot.n:
        got = "None" if q is None else shape_str(q.shape)
        raise ShapeError(f"expected q of shape (N, {robot.n}) for '{ref.name}' ({robot.n} joints), got {got}")
    given = None if fixture is None else torch.as_tensor(fixture)
    F = 1 if given is None or not given.numel() or given.is_floating_point() else int(given.max()) + 1
    q, onehot = _postures(ref, q, fixture, F)
    q = q.detach()
    (tip,) = tensors(("tip", [0.0, 0.0, 0.0] if tip is None else tip, (3,)), like=ref)
    if tip.ndim != 1:
        raise ShapeError(f"expected tip of shape (3,), got {shape_str(tip.shape)}")
    known = None
    if radius is not None:
        (known,) = tensors(("radius", radius, None), like=ref)
        known = known.reshape(-1).expand(F) if known.numel() == 1 else known.reshape(-1)
        if known.shape != (F,) or not bool((known > 0).all()):
            raise DiffkinError(f"expected radius > 0 as one number or {F} (one per sphere), got "
                               f"{known.tolist()}")
    count = onehot.sum(0)
    need = 3 if surface == "plane" else (4 if known is None else 3)
    if bool((count < need).any()):
        f = int((count < need).nonzero()[0])
        raise DiffkinError(f"{surface} {f} is touched in {int(count[f])} postures; at least {need} are "
                           "needed to locate it (and more than the robot's parameters to calibrate)")
    with torch.no_grad():
        p0 = tip_positions(ref, q, tip)
        w = onehot.transpose(0, 1)[..., None]
        d = p0 - (w * p0).sum(-2, keepdim=True) / count[:, None, None]
        spread = torch.linalg.eigvalsh((w * d).transpose(-1, -2) @ d)  # (F, 3) ascending
    # a sphere of unknown radius needs tips off one plane, a plane (or a known radius) off one line
    axis = 0 if surface == "sphere" and known is None else 1
    flat = spread[:, axis] <= 1e-12 * spread[:, 2].clamp_min(torch.finfo(q.dtype).tiny)
    if bool(flat.any()):
        f = int(flat.nonzero()[0])
        raise DiffkinError(f"the nominal tips of {surface} {f} lie on a degenerate set ("
                           f"{'one plane' if axis == 0 else 'one line'}): touch it at spread-out points")
    with torch.no_grad():
        values0, frames0 = fit_fixtures(p0, onehot, surface)
    model = ContactModel(robot, surface, tip, values0, frames0, known)
    x = torch.cat((q, onehot), -1)
    measured = q.new_zeros(q.shape[0], 1)
    scale = solver_options.pop("scale", None if sigma is None else 2 * sigma)
    loss, scale = resolve_loss(method, loss, scale, None, 0.0, True)
    opts = dict(max_iterations=max_iterations, tol=tol, progress=progress, loss=loss, scale=scale,
                **solver_options)
    opts = {k: v for k, v in opts.items() if v is not None}
    theta0 = model.nominal[None].clone()
    reports, free = contact_reports(model, theta0, x[None], rank_tol)
    report = reports[0]
    solve = least_squares if method == "least_squares" else gradient_descent
    out = solve(model, theta0, free, x[None], measured[None], orientation_weight=1.0, **opts)
    theta = out.zeta[0]

    # --------------------------------------------------------------------------------------- report
    with torch.no_grad():
        d = model.distances(theta[None], x[None])[0, :, 0]
    norms = d.abs()
    threshold = 3.0 * (sigma if sigma is not None else _MEDIAN_TO_SIGMA * float(norms.median()))
    outliers = (norms > threshold).nonzero().flatten().tolist()
    notes = list(model.notes)
    ratio = None
    if sigma is not None:
        robust = loss != "l2" and 0 < len(outliers) < norms.numel() / 2
        keep = norms <= threshold if robust else slice(None)
        kept = norms[keep]
        ratio = math.sqrt(float((kept / sigma).square().sum()) / max(kept.numel() - report.rank, 1))
        if ratio > 2.0:
            warnings.warn(
                f"contact calibration of '{ref.name}' (error model {kind!r}): the distance residual is "
                f"{ratio:.1f}x what {sigma * 1e3:g} mm of probe noise explains. Likely causes: wrong joint "
                "readings (order, units, timing), postures assigned to the wrong fixture, a moved fixture, "
                "a wrong tip or radius, or outliers (use loss='huber' or 'cauchy').",
                UserWarning, stacklevel=2)
    N = q.shape[0]
    if report.undetermined:
        notes.append(_undetermined_note(report, N))
        warnings.warn(f"contact calibration of '{ref.name}': {notes[-1]}", UserWarning, stacklevel=2)
    cv = None
    if cross_validation and N >= 4 * int(cross_validation):
        cv = _cross_validate(model, theta0, free, x, measured, solve, opts, int(cross_validation))
    chain_out = model.to_chains(theta[None])[0]
    nominal_copy = ref.copy()
    rms = float(d.square().mean().sqrt())
    failures = fit_failures(
        rms, None, None if cv is None else {"folds": cv["folds"], "position_rms": cv["distance_rms"]}, ratio,
        None if sigma is None else (sigma / math.sqrt(3),))
    wrong, end = correction_findings(nominal_copy, chain_out, q, max_correction)
    failures += wrong
    if end is not None:
        notes.append(end)
        warnings.warn(f"contact calibration of '{ref.name}': {end}", UserWarning, stacklevel=2)
    failure = "; ".join(failures) or None
    if failure is not None:
        warnings.warn(f"contact calibration of '{ref.name}' FAILED (result.success is False): {failure}",
                      UserWarning, stacklevel=2)
    cand = model.candidate.nonzero().flatten().tolist()
    length = model.is_length().tolist()
    fixtures = model.fixtures(theta).detach()
    return ContactCalibrationResult(
        chain=chain_out, nominal_chain=nominal_copy, method=method,
        names=[model.names[j] for j in cand], units=["m" if length[j] else "rad" for j in cand],
        nominal=theta0[0, cand].clone(), identified=theta[cand].detach().clone(), report=report,
        residuals=[float(h[0]) for h in out.position_rms], orientation_residuals=None,
        iterations=out.iterations, converged=bool(out.converged[0]), q=q, measured=measured[:, 0],
        error_model=kind, noise_ratio=ratio, cross_validation=cv, notes=notes, loss=loss, outliers=outliers,
        outlier_threshold=threshold, pose_position_errors=norms, pose_orientation_errors=None,
        success=failure is None, failure=failure, surface=surface, fixtures=fixtures,
        initial_fixtures=model.fixtures(theta0[0]).detach(), fixture=onehot.argmax(-1), tip=tip,
    )


def _cross_validate(model, theta0, free, x, measured, solve, opts, folds: int) -> dict | None:
    """k-fold held-out distance RMS over contacts; the k fits run as one batch."""
    fits = fold_fits(model, theta0, free, x, measured, solve, opts, folds, min_train=int(free.sum()) // 2 + 1)
    if fits is None:
        return None
    out, test = fits
    with torch.no_grad():
        d = model.distances(out.zeta, x[test])
    return {"folds": test.shape[0], "distance_rms": float(d.square().mean().sqrt()),
            "distance_max": float(d.abs().max())}


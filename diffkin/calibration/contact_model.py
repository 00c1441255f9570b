"""Measurement model of calibration from contacts: a probe tip on fixed spheres or planes in several postures
(:func:`~diffkin.calibration.calibrate_contacts`).

A touch probe (or a tool tip in a kinematic socket, a ball in a cup) gives no position, only that the tip
is on a surface: per posture one signed distance, whose measured value is zero. The parameter vector θ of
:class:`ContactModel` is, in this order::

    θ = [ζ (the robot's error model, P entries: calibrate's),
         per fixture f: sphere{f}_x, sphere{f}_y, sphere{f}_z, sphere{f}_r    centre and radius (m), or
                        plane{f}_z, plane{f}_rx, plane{f}_ry     T_f = T_f,0 · Δ(0, 0, z, rx, ry, 0)]

and the distance of posture i (touching fixture f) is, with p(ζ, q) = R_e(ζ, q) t + p_e(ζ, q) the tip
(``t``: the tip in the chain's end frame),

    sphere:  d_i = |p − c_f| − r_f                   (Euclidean distance to the sphere, signed)
    plane:   d_i = n_fᵀ (p − o_f)                    (n_f, o_f: the z axis and origin of T_f)

The plane's frame T_f,0 is the fit to the nominal tips (origin at their centroid, z the normal); only the
three corrections that move the plane are parameters (a shift along the normal and two tilts), so the
identifiability analysis names what the robot's geometry cannot be told from, not the plane's own gauge.

Identifiability is analysed (:func:`contact_reports`) at postures *on* the fixtures: a distance that is zero
at every contact has symmetries that distances at arbitrary postures do not show — most of all the scale:
all lengths of a revolute robot, the fixture's position and its radius times s give the same zero distances,
so with an unknown radius (or planes only) one length is unidentifiable and reported (a known radius, or a
known length kept out of the estimate, fixes the scale).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..kernels.joints import pose_correction
from ..transforms import _make_transform
from .identifiability import IdentifiabilityReport, _random_configurations, analyse_matrices, merge_reports
from .model import ParameterLayout, parameter_jacobian

__all__ = ["ContactModel", "SURFACES", "contact_reports", "fit_fixtures", "on_fixtures", "signed_distance",
           "tip_positions"]

#: the fixtures a probe tip can touch
SURFACES = ("sphere", "plane")
_AXES = {"sphere": ("x", "y", "z", "r"), "plane": ("z", "rx", "ry")}


def _plane_frames(normal: Tensor, origin: Tensor) -> Tensor:
    """``(F, 4, 4)`` frames with z = ``normal (F, 3)`` (unit) at ``origin (F, 3)``; x the projection of the
    base axis least aligned with the normal (any in-plane axis serves: the plane's gauge is not estimated)."""
    e = torch.eye(3, dtype=normal.dtype, device=normal.device)
    pick = torch.where((normal[..., :1].abs() < 0.9), e[0], e[1])
    x = pick - (pick * normal).sum(-1, keepdim=True) * normal
    x = x / x.norm(dim=-1, keepdim=True)
    R = torch.stack((x, torch.linalg.cross(normal, x), normal), -1)
    return _make_transform(R, origin)


def fit_fixtures(p: Tensor, onehot: Tensor, surface: str) -> tuple[Tensor, Tensor]:
    """Starting fixtures from tips ``p (N, 3)`` and the fixture of each ``onehot (N, F)``, all fixtures in
    one batched solve: ``(values (F, 4), frames (F, 4, 4))``.

    Sphere: the algebraic fit |p|² = 2 pᵀc + k, r = √(k + |c|²) (linear least squares), values [c, r];
    plane: the centroid m and the normal n of least variance (total least squares), values [n, nᵀm] and the
    frames of :func:`_plane_frames` (sphere: identity frames at c).
    """
    w = onehot.transpose(0, 1)[..., None]  # (F, N, 1)
    count = w.sum(-2)  # (F, 1)
    if surface == "sphere":
        a = torch.cat((2 * p, torch.ones_like(p[..., :1])), -1)  # (N, 4)
        A = (w * a).transpose(-1, -2) @ a  # (F, 4, 4)
        b = (w * a).transpose(-1, -2) @ p.square().sum(-1, keepdim=True)  # (F, 4, 1)
        sol = torch.linalg.solve(A, b)[..., 0]
        c = sol[..., :3]
        r = (sol[..., 3] + c.square().sum(-1)).clamp_min(0).sqrt()
        eye = torch.eye(3, dtype=p.dtype, device=p.device).expand(c.shape[0], 3, 3)
        return torch.cat((c, r[..., None]), -1), _make_transform(eye, c)
    m = (w * p).sum(-2) / count  # (F, 3)
    d = p - m[:, None, :]  # (F, N, 3)
    _, V = torch.linalg.eigh((w * d).transpose(-1, -2) @ d)
    n = V[..., 0]  # the direction of least spread
    return torch.cat((n, (n * m).sum(-1, keepdim=True)), -1), _plane_frames(n, m)


class ContactModel(ParameterLayout):
    """Signed distances of a probe tip to its fixtures for K robots: ``calibration_matrix``, ``residual``,
    ``residual_of`` and the layout the solvers of :mod:`.solvers` use (``n_params``, ``candidate``, ``names``,
    ``nominal``, ``is_length``, ``chains``), as :class:`~diffkin.calibration.camera_model.CameraModel`.

    ``robot``: the robot's error model (:func:`.error_models.build_model`); ``surface``: ``"sphere"`` or
    ``"plane"``; ``tip (3,)`` in the end frame; ``values0 (F, 4)`` and ``frames0 (F, 4, 4)`` of
    :func:`fit_fixtures`; ``radius (F,)`` known radii (sphere; None: estimated). The per-posture input is
    x_i = [q_i, one-hot of its fixture (F)], so the solvers take subsets of postures as they take poses.
    """

    def __init__(self, robot, surface: str, tip: Tensor, values0: Tensor, frames0: Tensor,
                 radius: Tensor | None = None):
        self.robot, self.surface, self.tip = robot, surface, tip
        self.frames0 = frames0
        self.n = robot.n
        self.F = values0.shape[0]
        self.P_robot = robot.n_params
        self.chains = robot.chains
        self.notes = list(getattr(robot, "notes", []))
        nominal_robot = robot.nominal if robot.nominal.ndim == 1 else robot.nominal[0]
        axes = _AXES[surface]
        if surface == "sphere":
            r = values0[:, 3] if radius is None else radius
            fixtures = torch.cat((values0[:, :3], r[:, None]), -1)
            free = torch.tensor([True, True, True, radius is None], device="cpu").repeat(self.F)
            length = torch.ones(4 * self.F, dtype=torch.bool, device="cpu")
        else:
            fixtures = values0.new_zeros(self.F, 3)  # corrections on the fitted frames
            free = torch.ones(3 * self.F, dtype=torch.bool, device="cpu")
            length = torch.tensor([True, False, False], device="cpu").repeat(self.F)
        self.nominal = torch.cat((nominal_robot, fixtures.reshape(-1).to(nominal_robot)))
        self.names = tuple(robot.names) + tuple(f"{surface}{f}_{a}" for f in range(self.F) for a in axes)
        self._length = torch.cat((robot.is_length().cpu(), length))
        self.candidate = torch.cat((robot.candidate.cpu(), free)).to(self.nominal.device)

    def fixtures(self, theta: Tensor) -> Tensor:
        """``(..., F, 4)`` of ``theta (..., P)``: sphere [c, r]; plane [n, nᵀo] (the plane is nᵀp = d)."""
        v = theta[..., self.P_robot :].unflatten(-1, (self.F, -1))
        if self.surface == "sphere":
            return v
        z = torch.zeros_like(v[..., :1])
        T = self.frames0 @ pose_correction(torch.cat((z, z, v, z), -1))
        n, o = T[..., :3, 2], T[..., :3, 3]
        return torch.cat((n, (n * o).sum(-1, keepdim=True)), -1)

    # ------------------------------------------------------------------------------ kinematics
    def tips(self, zeta: Tensor, q: Tensor) -> Tensor:
        """Tip positions ``(N, 3)`` of one robot's ``zeta (P_robot,)`` at ``q (N, n)``."""
        T = self.robot._fk_one(zeta, q)
        return (T[..., :3, :3] @ self.tip[:, None])[..., 0] + T[..., :3, 3]

    def _distance_one(self, theta: Tensor, x: Tensor) -> Tensor:
        """Signed distances ``(N, 1)`` of one robot at inputs ``x (N, n + F)``."""
        p = self.tips(theta[: self.P_robot], x[..., : self.n])
        fix = x[..., self.n :] @ self.fixtures(theta)  # (N, 4): each posture's fixture (one-hot rows)
        return signed_distance(p, fix, self.surface)[..., None]

    def distances(self, theta: Tensor, x: Tensor) -> Tensor:
        """Signed distances ``(K, N, 1)`` of ``theta (K, P)`` at ``x (K, N, n + F)``."""
        if theta.shape[0] == 1:  # one robot (the fit; cross-validation batches): no vmap overhead
            return self._distance_one(theta[0], x[0])[None]
        return torch.func.vmap(self._distance_one)(theta, x)

    def residual_of(self, prediction: Tensor, measured: Tensor, orientation_weight: float = 1.0) -> Tensor:
        """``(K, N, 1)``: measured (zero: a contact) minus predicted distance."""
        return measured - prediction

    def residual(self, theta: Tensor, x: Tensor, measured: Tensor, orientation_weight: float = 1.0) -> Tensor:
        return self.residual_of(self.distances(theta, x), measured)

    def calibration_matrix(self, theta: Tensor, x: Tensor, position_only: bool = False,
                           orientation_weight: float = 1.0, columns: Tensor | None = None):
        """Φ ``(K, N, 1, C)`` (distance per unit change of the selected entries of θ) and the distances."""
        with torch.no_grad():
            d = self.distances(theta, x)
        return parameter_jacobian(self._distance_one, theta, x, self.n_params, columns), d

    def to_chains(self, theta: Tensor):
        return self.robot.to_chains(theta[..., : self.P_robot])


def signed_distance(p: Tensor, fixture: Tensor, surface: str) -> Tensor:
    """Signed distance ``(...)`` of points ``p (..., 3)`` to their fixtures ``(..., 4)`` ([c, r] of a sphere,
    [n, d] of a plane nᵀp = d); the sphere's |p − c| with a finite derivative at p = c (no NaN)."""
    if surface == "sphere":
        d = p - fixture[..., :3]
        return d.square().sum(-1).clamp_min(torch.finfo(d.dtype).tiny).sqrt() - fixture[..., 3]
    return (fixture[..., :3] * p).sum(-1) - fixture[..., 3]


def tip_positions(chain, q: Tensor, tip: Tensor) -> Tensor:
    """``(..., 3)``: the point ``tip (3,)`` of the end frame of ``chain`` at ``q (..., n)``."""
    T = chain.forward_kinematics(q)
    return (T[..., :3, :3] @ tip[:, None])[..., 0] + T[..., :3, 3]


def on_fixtures(chain, tip: Tensor, surface: str, fixtures: Tensor, q: Tensor, fixture: Tensor,
                iterations: int = 20) -> tuple[Tensor, Tensor]:
    """Move ``q (M, n)`` until the tip of ``chain`` touches its fixture (``fixtures (F, 4)`` as
    :func:`signed_distance`, index ``fixture (M,)``): Gauss–Newton on the one distance per posture
    (minimum-norm joint step −d ∇d / |∇d|², at most 0.5 rad a joint), all postures at once. Returns
    ``(q (M, n), on (M,) bool)``: ``on`` where |d| fell below √ε times the tip's reach (+ 1 m)."""
    fix = fixtures.detach()[fixture]
    tiny = torch.finfo(q.dtype).tiny
    q = q.detach().clone()
    with torch.no_grad():
        reach = 1.0 + float(tip_positions(chain, q, tip).norm(dim=-1).max())
    tol = math.sqrt(torch.finfo(q.dtype).eps) * reach
    for _ in range(iterations):
        with torch.enable_grad():
            qg = q.requires_grad_(True)
            d = signed_distance(tip_positions(chain, qg, tip), fix, surface)
            (g,) = torch.autograd.grad(d.sum(), qg)  # postures are independent: row i is ∇d_i
        d, q = d.detach(), q.detach()
        if bool((d.abs() <= 1e-3 * tol).all()):
            break
        step = d[:, None] * g / g.square().sum(-1, keepdim=True).clamp_min(tiny)
        q = q - step.clamp(-0.5, 0.5)
    with torch.no_grad():
        d = signed_distance(tip_positions(chain, q, tip), fix, surface)
    return q, d.abs() <= tol


def contact_reports(model: ContactModel, theta: Tensor, x: Tensor, rank_tol: float | None = None
                    ) -> tuple[list[IdentifiabilityReport], Tensor]:
    """Identifiability of K robots (``theta (K, P)`` at inputs ``x (K, N, n + F)``) and the free mask
    ``(K, C)``, as :func:`.camera_model.camera_reports`: structurally at random postures moved onto the
    fixtures (:func:`on_fixtures`; what no set of contacts determines is fixed at its start and reported
    with its dependencies, the fixtures' columns first so that a robot parameter is named against the
    fixture that absorbs it); then at the given postures (``undetermined``: minimum-norm estimates)."""
    K, N = x.shape[0], x.shape[1]
    cand = model.candidate.cpu()
    names = model.names
    P = model.P_robot
    idx = cand.nonzero().flatten().tolist()
    order = [j for j in idx if j >= P] + [j for j in idx if j < P]
    order_names = [names[j] for j in order]
    pos = {j: k for k, j in enumerate(idx)}
    perm = [pos[j] for j in order]
    C = len(idx)
    with torch.no_grad():
        M = 3 * C + 24  # one row per posture: some postures fail to reach a fixture
        qs = _random_configurations(model.robot, M, theta.dtype, theta.device)
        fixture = torch.arange(M, device=theta.device) % model.F
        structs, data = [], []
        Phi_d, _ = model.calibration_matrix(theta, x, columns=model.candidate)
        Phi_d = Phi_d[..., perm].reshape(K, -1, C)
        for k in range(K):  # K is 1 but for cross-validation, which does not analyse
            chain = model.to_chains(theta[k : k + 1])[0]
            qk, on = on_fixtures(chain, model.tip, model.surface, model.fixtures(theta[k]), qs, fixture)
            xs = torch.cat((qk, torch.nn.functional.one_hot(fixture, model.F).to(qk)), -1)[on]
            Phi_s, _ = model.calibration_matrix(theta[k : k + 1], xs[None], columns=model.candidate)
            st = analyse_matrices(Phi_s[..., perm].reshape(1, -1, C), order_names, xs.shape[0], rank_tol)[0]
            structs.append(st)
            # the data's rank and conditioning over what is estimated: the nominal tips are off the fixtures
            # by the errors being calibrated, so a structural null direction (the scale) is not exactly
            # null there and would only blur the condition number
            keep = [i for i, nm in enumerate(order_names) if nm not in set(st.unidentifiable)]
            data += analyse_matrices(Phi_d[k : k + 1, :, keep], [order_names[i] for i in keep], N, rank_tol)
    return merge_reports(data, structs, [names[j] for j in idx], 1, theta.device)

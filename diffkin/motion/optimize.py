"""Trajectory optimisation of a found path, and its implicit gradient (the optimisation stage of
:func:`diffkin.motion.plan`, ``optimize=True``).

**The problem.** The searched and shortcut path is resampled to M interior knots X = (x_1 … x_M) equally
spaced in the subdivision's metric Σ_j R_j |Δq_j| (:func:`~diffkin.motion.joint_reach`), between the fixed
ends x_0 = q_start and x_{M+1} = q_goal. With h = 1/(M+1) and the joint weights W = diag(R_j²)/mean(R²)
(so both terms measure geom travel),

    min_X  C(X) = ½ Σ_{k=0}^{M} ‖Δx_k‖²_W / h  +  ½ α Σ_{k=1}^{M} ‖Δ²x_k‖²_W / h³          (velocity and
                                                                                          acceleration energy)
    s.t.   d_i(x_k) ≥ margin + η + buffer    (the ``nearest`` smallest distances of each knot, self and world:
                                            :class:`~diffkin.ik.residuals.DistanceConstraint`)
           q_lo ≤ x_k ≤ q_hi.

C is the discrete ∫‖q'‖² + α∫‖q''‖² of a path with uniform parameter: without obstacles the straight
segment at uniform speed. The distances are the collision layer's closed forms (differentiable).

**The solver** (batched over problems; loops run over iterations, never rows): sequential quadratic
programming. Each step Δ solves

    min_Δ ½ Δᵀ(∇²C − Σ_i λ_i ∇²g_i)Δ + ∇Cᵀ Δ
    s.t.  g_i + ∇g_i·Δ ≥ 0 (a penetration recovered by at most 2 cm a step),  lo ≤ x + Δ ≤ hi,  |Δ| ≤ trust

(g_i = d_i − bound, the ``nearest`` rows of each knot; λ the last step's multipliers on the rows still
selected; the curvature Σλ_i∇²g_i per knot by forward differences of exact gradients, dropped where it
would make the Hessian indefinite). The QP is first solved as the KKT system of the last active set (one
solve, kept where primal and dual feasible), else by the interior point of :mod:`diffkin.ik._qp_ip`. The
trust region halves where a step turns back on the last one. A row converges when its largest step is
below ``tolerance``; its knots are then a KKT point.

**The gradient** is implicit, as :func:`diffkin.ik.optimize`'s (:mod:`diffkin.ik.implicit`, whose row
selection it reuses): the knots are a KKT point, and the rows held at the boundary with a positive
multiplier (and the coordinates held at a joint limit) are differentiated as equalities,
[∇²L Aᵀ; A 0][dX; dν] = −[∂_z∇_X L dz; ∂_z a dz] with L = C − λᵀd; z is the start, the goal, and every
tensor of the world that requires grad (sphere centres and radii, box poses and sizes, …). Every
second-order term is a central difference of exact gradients (:class:`_ImplicitKnots`): the collision
layer's autograd second derivatives are exact for spheres, capsules, boxes and half-spaces
(``tests/test_collision_second_order.py``) but not for convex meshes or a cylinder's rim search, whose witness
parameters are held constant (the envelope theorem holds for the first derivative only).

**Where it is not defined.** The gradient is that of the local solution: it holds while the set of rows
held does not change (a perturbation that makes a new distance row active, or releases one, is a kink:
the two one-sided derivatives differ) and it is blind to a change of homotopy class — a larger
perturbation for which the search, or the optimisation, goes round the other side of an obstacle lands on
another local solution that no derivative at this one predicts (the planner's path jumps).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..collision.world import World
from ..ik._qp_ip import _polish, ip_solve
from ..ik.residuals import DistanceConstraint, _residual_jacobian
from ..validation import check_count, check_number
from ._spline import _knots, _spline_clear

__all__ = ["OptimizeConfig", "OptimizedPath", "optimize_knots", "optimize_stage", "resample", "sample_with"]

_PUSH = 0.02  # the most a penetrating distance row is asked to recover in one step [m]


@dataclass(frozen=True)
class OptimizeConfig:
    """Knobs of the optimisation stage (module docstring).

    Attributes:
        knots: M, the interior knots (the optimised path has M + 2 waypoints).
        iterations: the most multiplier updates (Gauss–Newton steps).
        buffer: clearance [m] the knots keep above ``margin + resolution``: room for the segments between
            knots and for the spline through them (both re-checked by the proven subdivision; a row whose
            optimised path is not proven clear keeps its searched path).
        nearest: distance rows per knot in each step (the smallest ones).
        acceleration_weight: α, the weight of the acceleration energy.
        trust: the largest change of a joint in one step [rad].
        tolerance: the largest step [rad] of a converged row.
    """

    knots: int = 16
    iterations: int = 100
    buffer: float = 0.01
    nearest: int = 6
    acceleration_weight: float = 0.05
    trust: float = 0.1
    tolerance: float = 1e-11

    def __post_init__(self):  # the shared option validators (typed OptionError naming the field)
        for name in ("knots", "iterations", "nearest"):
            check_count(getattr(self, name), f"OptimizeConfig.{name}")
        for name in ("buffer", "acceleration_weight", "trust", "tolerance"):
            check_number(getattr(self, name), f"OptimizeConfig.{name}", positive=name == "trust")


@dataclass
class OptimizedPath:
    """Result of :func:`optimize_knots`: ``path (B, M + 2, nq)`` (the ends are the inputs themselves; the
    interior carries the implicit gradient), ``converged (B,)`` and the ``iterations`` run."""

    path: Tensor
    converged: Tensor
    iterations: int


def resample(path: Tensor, reach: Tensor, count: int) -> Tensor:
    """``count`` points ``(B, count, nq)`` equally spaced along the polylines ``path (B, L, nq)`` in the
    metric Σ_j R_j |Δq_j| (``reach (nq,)``), the first and last waypoints kept exactly (a path of zero
    length gives its start ``count`` times)."""
    seg = ((path[:, 1:] - path[:, :-1]).abs() * reach).sum(-1)  # (B, L-1)
    cum = torch.cat((torch.zeros_like(seg[:, :1]), seg.cumsum(1)), 1)  # (B, L)
    total = cum[:, -1:]
    u = torch.linspace(0, 1, count, dtype=path.dtype, device=path.device) * total  # (B, count)
    i = torch.searchsorted(cum[:, 1:-1].contiguous(), u.contiguous(), right=True)  # segment (B, count)
    c0, c1 = cum.gather(1, i), cum.gather(1, i + 1)
    f = ((u - c0) / (c1 - c0).clamp_min(torch.finfo(path.dtype).tiny)).clamp(0, 1)[..., None]
    idx = i[..., None].expand(*i.shape, path.shape[-1])
    out = path.gather(1, idx) + f * (path.gather(1, idx + 1) - path.gather(1, idx))
    out[:, 0], out[:, -1] = path[:, 0], path[:, -1]
    return out


def _smoothness(M: int, alpha: float, dtype, device) -> Tensor:
    """Q ``(M + 2, M + 2)`` of C = ½ Σ_j W_j Y_jᵀ Q Y_j over the knots Y (ends included)."""
    h = 1.0 / (M + 1)
    eye = torch.eye(M + 2, dtype=dtype, device=device)
    D1 = eye[1:] - eye[:-1]
    D2 = eye[2:] - 2 * eye[1:-1] + eye[:-2]
    return D1.T @ D1 / h + alpha * (D2.T @ D2) / h**3


def _cost(Q: Tensor, W: Tensor, Y: Tensor) -> Tensor:
    """C ``(B,)`` of knots Y ``(B, M + 2, nq)`` (module docstring)."""
    return 0.5 * ((Q @ Y) * Y * W).sum((-1, -2))


def _detached(world: World | None, dtype) -> World | None:
    if world is None:
        return None
    return world._map(lambda t, own: t.detach().to(dtype))  # registered object kinds included


class _Rows:
    """The distance rows g_i = d_i − bound of knots X ``(B, M, nq)`` (a world of batch ``()`` or ``(B,)``:
    the knots go knot-major through the collision layer so that the world's batch meets the problems)."""

    def __init__(self, constraint: DistanceConstraint, bound: float):
        self.c, self.bound = constraint, bound

    def all(self, X: Tensor, threshold: float | None = None) -> Tensor:
        """g ``(..., B, M, D)`` of X ``(..., B, M, nq)`` (exact below ``threshold`` above the bound; None:
        exact)."""
        d = self.c.distances(X.transpose(-3, -2), None if threshold is None else self.bound + threshold)
        return d.transpose(-3, -2) - self.bound

    def curvature(self, X: Tensor, rows: Tensor, lam: Tensor, detection: float, h: float = 1e-6) -> Tensor:
        """Σ_i λ_i ∇²g_i ``(B, M, nq, nq)`` of the ``rows`` ``(B, M, k)`` with weights ``lam`` per knot (each
        row depends on its knot only): forward differences of the weighted gradient along each joint, the
        nq + 1 points in one evaluation (error O(h) relative)."""
        nq = X.shape[-1]
        steps = torch.cat((X.new_zeros(1, nq), h * torch.eye(nq, dtype=X.dtype, device=X.device)))
        with torch.enable_grad():
            Xs = (X[None] + steps[:, None, None, :]).requires_grad_(True)  # (nq + 1, B, M, nq)
            g = self.all(Xs, detection)
            phi = (g.gather(-1, rows.expand(nq + 1, *rows.shape)) * lam).sum()
            (gr,) = torch.autograd.grad(phi, Xs)
        Hc = ((gr[1:] - gr[:1]) / h).permute(1, 2, 3, 0)  # (B, M, nq_i, nq_j): column j from joint j
        return 0.5 * (Hc + Hc.mT)

    def nearest(self, X: Tensor, k: int, detection: float) -> tuple[Tensor, Tensor, Tensor]:
        """(g ``(B, M, k)``, rows ``(B, M, k)`` into D, ∂g/∂x ``(B, M, k, nq)``) of the k smallest rows."""
        with torch.enable_grad():
            Xg = X.detach().requires_grad_(True)
            g = self.all(Xg, detection)
            k = min(k, g.shape[-1])
            rows = g.detach().topk(k, dim=-1, largest=False).indices
            sel = g.gather(-1, rows)
            J = _residual_jacobian(sel, Xg)  # each row depends on its own knot only: per-sample Jacobians
        return sel.detach(), rows, J.detach()


def _qp(H: Tensor, c: Tensor, G: Tensor, h: Tensor, guess: Tensor | None) -> tuple[Tensor, Tensor]:
    """min ½xᵀHx − cᵀx s.t. Gx ≤ h (x, λ): first the KKT system of the active set ``guess`` (the last
    iteration's, usually right near the solution: one solve), kept where it is primal and dual feasible
    (:func:`~diffkin.ik._qp_ip._polish`'s test); the interior point of :mod:`diffkin.ik._qp_ip` for the
    other problems."""
    B = H.shape[0]
    good = torch.zeros(B, dtype=torch.bool, device=H.device)
    x, lam = c.new_zeros(c.shape), h.new_zeros(h.shape)
    if guess is not None:
        on = torch.ones_like(guess)
        x, lam, _, good = _polish(H, c, G, h, on, x, torch.full_like(h, 0.5), guess.to(h.dtype))
    if not bool(good.all()):
        bad = (~good).nonzero().squeeze(1)
        xb, lb, _, _ = ip_solve(H[bad], c[bad], G[bad], h[bad], 40)
        x, lam = x.index_put((bad,), xb), lam.index_put((bad,), lb)
    return x, lam


def _solve(rows: _Rows, Q: Tensor, W: Tensor, Y: Tensor, lo: Tensor, hi: Tensor, cfg: OptimizeConfig
           ) -> tuple[Tensor, Tensor, Tensor, Tensor, int, Tensor]:
    """The sequential-QP iterations (module docstring) from knots Y ``(B, M + 2, nq)`` (float64, ends
    fixed): (Y, multipliers λ ``(B, M, k)`` of the last QP's distance rows, those rows (indices into D),
    their g, iterations, converged ``(B,)``)."""
    B, N, nq = Y.shape
    M, n = N - 2, (N - 2) * nq
    k = cfg.nearest
    detection = 0.1  # rows farther than this hold a lower bound (never active in one step: at most trust·ΣR)
    QW = torch.kron(Q[1:-1, 1:-1].contiguous(), torch.diag(W)).expand(B, n, n)  # ∇²C, knot-major
    X = Y[:, 1:-1].clone()
    ends = Y[:, [0, -1]]
    converged = torch.zeros(B, dtype=torch.bool, device=Y.device)
    trust = torch.full((B, 1, 1), cfg.trust, dtype=Y.dtype, device=Y.device)
    prev = torch.zeros_like(X)
    it = 0
    lam = idx = None
    lam_box = Y.new_zeros(B, 2 * n)
    ar = torch.arange(M, device=Y.device)
    for it in range(1, cfg.iterations + 1):  # noqa: B007 (the count is returned)
        g, new_idx, J = rows.nearest(X, k, detection)
        k = g.shape[-1]
        H = QW
        li = None
        if lam is not None:  # the last QP's multipliers on the rows still selected (new rows: 0)
            li = ((new_idx[..., :, None] == idx[..., None, :]).to(g.dtype) * lam[..., None, :]).sum(-1)
        if li is not None and bool((li > 0).any()):
            # ∇²L = ∇²C − Σ λ_i ∇²g_i: Newton's rate on the Lagrangian (Gauss–Newton's alone is linear,
            # slow where the distances curve)
            curv = rows.curvature(X, new_idx, li, detection)
            Hl = QW.clone()
            Hl.view(B, M, nq, M, nq)[:, ar, :, ar, :] -= curv.transpose(0, 1)
            pd = torch.linalg.cholesky_ex(Hl)[1] == 0  # else Gauss–Newton's (the QP needs H > 0)
            H = torch.where(pd[:, None, None], Hl, QW)
        idx = new_idx
        Yc = torch.cat((ends[:, :1], X, ends[:, 1:]), 1)
        grad_c = ((Q @ Yc) * W)[:, 1:-1].reshape(B, n)  # ∇C
        # rows: −J Δ ≤ g (g + JΔ ≥ 0; a penetration recovered by at most `push` a step), then the box
        # of the limits and the trust region
        Gd = torch.zeros(B, M, k, M, nq, dtype=Y.dtype, device=Y.device)
        Gd[:, ar, :, ar, :] = -J.transpose(0, 1)
        eye = torch.eye(n, dtype=Y.dtype, device=Y.device).expand(B, n, n)
        G = torch.cat((Gd.reshape(B, M * k, n), eye, -eye), 1)
        up = torch.minimum(hi - X, trust).clamp_min(0).reshape(B, n)
        down = torch.minimum(X - lo, trust).clamp_min(0).reshape(B, n)
        h = torch.cat((g.clamp_min(-_PUSH).reshape(B, M * k), up, down), 1)
        guess = None if li is None else torch.cat((li.reshape(B, M * k) > 0, lam_box > 0), 1)
        step, lam_all = _qp(H, -grad_c, G, h, guess)
        lam, lam_box = lam_all[:, : M * k].reshape(B, M, k), lam_all[:, M * k:]
        step = step.view(B, M, nq)
        # the trust region halves where the step turns back on the last one (a cycle between two sets of
        # rows), and grows back to cfg.trust while it does not
        back = (step * prev).sum((1, 2)) < -0.5 * (step * step).sum((1, 2))
        trust = torch.where(back[:, None, None], 0.5 * trust, (1.5 * trust).clamp(max=cfg.trust))
        prev = step
        X = torch.where(converged[:, None, None], X, torch.maximum(torch.minimum(X + step, hi), lo))
        converged = converged | (step.abs().flatten(1).amax(1) <= cfg.tolerance)
        if bool(converged.all()):
            break
    Y = torch.cat((ends[:, :1], X, ends[:, 1:]), 1)
    return Y, lam, idx, g, it, converged


def optimize_knots(collision, world: World | None, q_start: Tensor, q_goal: Tensor, path: Tensor,
                   lo: Tensor, hi: Tensor, bound: float, reach: Tensor, cfg: OptimizeConfig | None = None,
                   warm: Tensor | None = None) -> OptimizedPath:
    """Optimised knots (module docstring) of the paths ``path (B, L, nq)`` from ``q_start`` to ``q_goal``
    ``(B, nq)`` (the path's own ends are replaced by them), with every distance row ≥ ``bound`` [m]
    (``margin + resolution + buffer``), within the joint limits ``lo``, ``hi`` ``(nq,)`` (±inf allowed), in
    ``world`` (batch ``()`` or ``(B,)``). ``reach (nq,)``: the subdivision's R_j (the metric of the
    resampling and the joint weights). ``warm``: knots ``(B, M + 2, nq)`` of an earlier result (same
    problems) to start from instead of the resampled path (a re-optimisation from that solution).

    Computed in float64 (the result in ``q_start``'s dtype). With grad mode on and ``q_start``, ``q_goal``
    or a tensor of ``world`` requiring grad, the interior knots carry the implicit gradient (module
    docstring); the ends are ``q_start`` and ``q_goal`` themselves. Rows that did not converge get a zero
    gradient for their interior knots."""
    cfg = cfg or OptimizeConfig()
    f64, dtype = torch.float64, q_start.dtype
    B, nq = q_start.shape
    M = cfg.knots
    R = reach.detach().to(f64)
    W = (R**2) / (R**2).mean().clamp_min(1e-300)
    Q = _smoothness(M, cfg.acceleration_weight, f64, q_start.device)
    coll64 = collision
    if collision.capsule_radius.dtype != f64:
        coll64 = DistanceConstraint(collision, None).to(f64).collision
    moving = DistanceConstraint(coll64, _detached(world, f64), 0.0)
    rows = _Rows(moving, float(bound))
    lo64, hi64 = lo.detach().to(f64), hi.detach().to(f64)
    with torch.no_grad():
        Y0 = resample(path.detach().to(f64), R, M + 2) if warm is None else warm.detach().to(f64).clone()
        Y0[:, 0], Y0[:, -1] = q_start.detach().to(f64), q_goal.detach().to(f64)
        Y, lam, idx, g, it, converged = _solve(rows, Q, W, Y0, lo64, hi64, cfg)
    X = Y[:, 1:-1].reshape(B, M * nq)
    z = torch.cat((q_start, q_goal), -1).to(f64)
    params = () if world is None else tuple(t for t in world.tensors() if t.requires_grad)
    if torch.is_grad_enabled() and (z.requires_grad or params):
        X = _attach(coll64, world, Q, W, Y, lam, idx, g, lo64, hi64, converged, z, params, float(bound))
    X = X.reshape(B, M, nq).to(dtype)
    full = torch.cat((q_start[:, None], X, q_goal[:, None]), 1)
    return OptimizedPath(full, converged, it)


def _attach(coll64, world, Q, W, Y, lam, idx, g, lo, hi, converged, z, params, bound) -> Tensor:
    """The interior knots ``(B, M·nq)`` carrying the implicit gradient w.r.t. z = (q_start, q_goal) and
    ``params`` (the world's tensors that require grad): the KKT rows are the distance rows the last QP held
    with a positive multiplier (g ≈ 0), and the coordinates at a joint limit."""
    B, N, nq = Y.shape
    M = N - 2
    X = Y[:, 1:-1].reshape(B, M * nq)
    held = (lam > 0) & (g.abs() <= 1e-6)
    with torch.no_grad():
        D = DistanceConstraint(coll64, _detached(world, torch.float64), 0.0).distances(
            Y[:1, 1:2].transpose(0, 1)).shape[-1]
    flat = torch.arange(M, device=Y.device)[None, :, None] * D + idx  # (B, M, k): knot·D + row
    r = int(held.flatten(1).sum(1).max()) if B else 0
    order = torch.argsort((~held).flatten(1).to(torch.int8), dim=1, stable=True)[:, :r]
    rows_idx = flat.flatten(1).gather(1, order)  # (B, r), the held rows first (padded with others)
    rows_on = held.flatten(1).gather(1, order)
    # coordinates at a limit: a = x (lower) or −x (upper), on the union of such coordinates over the batch
    at_lo, at_hi = X <= lo.repeat(M), X >= hi.repeat(M)
    cols = (at_lo | at_hi).any(0).nonzero().squeeze(1)
    sign = torch.where(at_hi[:, cols], -1.0, 1.0).to(X.dtype)
    active = torch.cat((rows_on, (at_lo | at_hi)[:, cols]), 1)
    spec = (coll64, world, Q, W, rows_idx, cols, sign, active, converged, bound, D)
    return _ImplicitKnots.apply(X, z, spec, *params)


def _distance_rows(coll64, world, X: Tensor, rows_idx: Tensor, bound: float) -> Tensor:
    """g of the rows ``rows_idx (B, r)`` (flat knot·D + row) at knots X ``(..., B, M, nq)``:
    ``(..., B, r)``."""
    d = _Rows(DistanceConstraint(coll64, world, 0.0), bound).all(X)
    d = d.flatten(-2)
    return d.gather(-1, rows_idx.expand(*d.shape[:-1], rows_idx.shape[-1]))


class _ImplicitKnots(torch.autograd.Function):
    """dX* of the KKT point X* (module docstring): [∇²L Aᵀ; A 0][u; v] = [ḡ; 0] for the cotangent ḡ, then
    z̄ = −(uᵀ ∂_z∇_X L + vᵀ ∂_z a), L = C − λᵀa. The collision layer's distances have exact gradients but
    not, for every primitive, exact second derivatives (convex meshes and a cylinder's rim search hold their
    witness parameters constant), so every second-order term is a central difference of exact gradients
    along one direction: the curvature Σλ_i∇²d_i per knot along each joint, and
    uᵀ ∂_w∇_X(λᵀd) = ∂_w[(λᵀd(X + εu) − λᵀd(X − εu)) / 2ε] (ε = 1e-5 rad: error O(ε²) relative)."""

    @staticmethod
    def forward(ctx, X: Tensor, z: Tensor, spec: tuple, *params: Tensor) -> Tensor:
        ctx.spec = spec
        ctx.save_for_backward(X, z)
        return X.clone()

    @staticmethod
    def backward(ctx, gbar: Tensor):
        from ..ik.implicit import _active_constraints

        X, z = ctx.saved_tensors
        coll64, world, Q, W, rows_idx, cols, sign, active, converged, bound, D = ctx.spec
        B, n = X.shape
        nq = z.shape[-1] // 2
        M = n // nq
        wdet = _detached(world, torch.float64)
        eps = 1e-5
        gbar = gbar.to(X.dtype)
        ends = torch.stack((z[:, :nq], z[:, nq:]), 1).detach()
        Y = torch.cat((ends[:, :1], X.view(B, M, nq), ends[:, 1:]), 1)
        grad_c = ((Q @ Y) * W)[:, 1:-1].reshape(B, n)  # ∇C at the solution
        QW = torch.kron(Q[1:-1, 1:-1].contiguous(), torch.diag(W))
        r = rows_idx.shape[1]

        def a_fn(Xf: Tensor) -> Tensor:
            return torch.cat((_distance_rows(coll64, wdet, Xf.view(B, M, nq), rows_idx, bound),
                              sign * Xf[:, cols]), 1)

        if active.shape[1]:
            with torch.enable_grad():
                qv = X.detach().requires_grad_(True)
                # the rows held (independent, with λ > 0 in ∇C = Aᵀλ by least squares): ik's selection
                _, A, lam, keep = _active_constraints(a_fn, active, qv, grad_c)
            A, lam = A.detach(), lam.detach()
        else:  # nothing held: the unconstrained minimum
            A, lam, keep = X.new_zeros(B, 0, n), X.new_zeros(B, 0), active
        lam_d = lam[:, :r] * keep[:, :r].to(X.dtype)  # the distance rows' multipliers
        H = QW.expand(B, n, n).clone()
        if r:  # Σ λ_i ∇²d_i per knot: central differences of the exact gradient of λᵀd along each joint
            steps = eps * torch.eye(nq, dtype=X.dtype, device=X.device)
            Xs = (X.view(B, M, nq)[None] + torch.cat((steps, -steps))[:, None, None, :])
            with torch.enable_grad():
                Xs = Xs.requires_grad_(True)
                phi = (_distance_rows(coll64, wdet, Xs, rows_idx, bound) * lam_d).sum()
                (gr,) = torch.autograd.grad(phi, Xs)
            curv = ((gr[:nq] - gr[nq:]) / (2 * eps)).permute(1, 2, 3, 0)  # (B, M, nq_i, nq_j)
            ar = torch.arange(M, device=X.device)
            H.view(B, M, nq, M, nq)[:, ar, :, ar, :] -= (0.5 * (curv + curv.mT)).transpose(0, 1)
        m = A.shape[1]
        Am = A * keep[..., None].to(X.dtype)
        off = -torch.diag_embed((~keep).to(X.dtype))  # rows not held: ν = 0
        K = torch.cat((torch.cat((H, Am.mT), -1), torch.cat((Am, off), -1)), -2)
        rhs = torch.cat((gbar, gbar.new_zeros(B, m)), -1)
        uv, info = torch.linalg.solve_ex(K, rhs[..., None])
        ok = (converged & (info == 0))[:, None].to(X.dtype)
        uv = torch.nan_to_num(uv[..., 0]) * ok
        u, v = uv[:, :n], uv[:, n:] * keep.to(X.dtype)
        # the ends enter ∇C linearly: ∂(∇_X C)/∂q_start = Q[1:-1, 0] ⊗ W (q_goal: Q[1:-1, -1])
        uk = u.view(B, M, nq)
        g_start = -(Q[1:-1, 0][None, :, None] * W * uk).sum(1)
        g_goal = -(Q[1:-1, -1][None, :, None] * W * uk).sum(1)
        grad_z = torch.cat((g_start, g_goal), -1)
        params = ctx.spec[1].tensors() if len(ctx.needs_input_grad) > 3 else ()
        grads = [None] * (len(ctx.needs_input_grad) - 3)
        if grads and r:
            # z̄_w = ∂_w[uᵀ∇_X(λᵀd) − vᵀd] (∇_X L = ∇C − ∇_X(λᵀd)), the first term by a central difference
            wanted = [t for t in params if t.requires_grad]
            with torch.enable_grad():
                w64 = world.to(torch.float64)  # differentiable: the grads reach the world's own tensors
                Xu = X.view(B, M, nq)[None] + torch.stack((eps * uk, -eps * uk))
                dr = _distance_rows(coll64, w64, torch.cat((Xu, X.view(1, B, M, nq))), rows_idx, bound)
                s = ((dr[0] - dr[1]) / (2 * eps) * lam_d).sum() - (dr[2] * v[:, :r]).sum()
                grads = list(torch.autograd.grad(s, wanted, allow_unused=True))
        return (None, grad_z.to(z.dtype), None, *grads)


def optimize_stage(checker, world, q_start: Tensor, q_goal: Tensor, path: Tensor, rows: Tensor, lo: Tensor,
                   hi: Tensor, cfg: OptimizeConfig) -> tuple[Tensor, Tensor]:
    """:func:`diffkin.motion.plan`'s stage: the optimised knots ``(R, M + 2, nq)`` of the searched paths
    ``path (R, L, nq)`` of problems ``rows (R,)`` (``q_start``, ``q_goal`` ``(R, nq)``: the plan's inputs,
    which may carry gradients; ``world``: the plan's, batch ``()`` or ``(B,)``), and ``kept (R,)``: the rows
    whose optimised path is proven clear by ``checker`` (the :class:`~diffkin.motion._edges.EdgeChecker`):
    every straight segment between knots and the clamped spline through them (the path that is timed)
    within the joint limits ``lo``, ``hi``. A row whose iterations did not converge is kept on the same
    proof (its last iterate, a smoother path than the search's) but carries no gradient (it is no KKT
    point)."""

    w = world
    if world is not None and len(world.batch_shape):
        w = world._take(rows)
    bound = checker.margin + checker.eta + cfg.buffer
    out = optimize_knots(checker.collision, w, q_start, q_goal, path, lo, hi, bound, checker.reach, cfg)
    with torch.no_grad():
        Y = out.path.detach()
        R, N, nq = Y.shape
        free, _ = checker.edges(Y[:, :-1].reshape(-1, nq), Y[:, 1:].reshape(-1, nq),
                                rows.repeat_interleave(N - 1))
        kept = free.view(R, N - 1).all(1)
        kept &= _spline_clear(checker, Y, _knots(Y), lo, hi, rows)
    return out.path, kept


def sample_with(timed, path: Tensor, t: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """q, q̇, q̈ ``(R, T, nq)`` of the timed clamped spline ``timed`` (a
    :class:`~diffkin.trajectories.time_optimal.TimedPath`) with its waypoints replaced by ``path``
    ``(R, N, nq)`` (the same values, carrying gradients): the time law and the path parameters are held
    fixed, so the samples are linear in the waypoints and the gradient reaches them."""
    import copy

    from ..trajectories.time_optimal import _Path

    moved = copy.copy(timed)
    moved._path = _Path(timed._path.s, path.to(torch.float64), "spline", "clamped")
    q, qd, qdd, _ = moved._joint(t)
    return q.to(path.dtype), qd.to(path.dtype), qdd.to(path.dtype)

"""Differentiable IK against theseus-ai (implicit mode) on the same Panda targets in the same run.

    python -m benchmarks.bench_ik_theseus [--targets 1000] [--dtype float64] [--threads 1] [--quick]

Not registered in ``benchmarks.run`` (theseus is not a dependency). Install it outside the project venv,
without touching torch::

    python -m pip install --no-build-isolation --no-deps --target /tmp/thx theseus-ai==0.2.3
    python -m pip install --no-build-isolation --no-deps --target /tmp/thx-deps \\
        torchlie==0.1.0 torchkin==0.1.1 semantic-version==2.10.0 urdf_parser_py==0.0.4
    PYTHONPATH=.:/tmp/thx:/tmp/thx-deps python -m benchmarks.bench_ik_theseus

``scikit-sparse`` (theseus's CHOLMOD solver) is not needed: theseus imports without it (a warning) and this
benchmark uses its dense Cholesky solver.

Problem: Panda (``diffkin/models/data/panda.urdf``, end link ``panda_link8``), N random reachable full-pose
targets (FK of random joints within limits), one start ``q_start = q_true + U(-0.3, 0.3)`` rad per target
shared by both solvers (both run as local solvers: diffkin with ``num_seeds=1``), loss
``((q - q_true)**2).sum()`` on the solution, gradients w.r.t. the target poses.

* diffkin: ``ik.solve(chain, T.requires_grad_(), q0=q_start, num_seeds=1)`` (LM, joint limits on,
  implicit backward through the minimum-norm J⁺ at the solution).
* theseus: ``th.LevenbergMarquardt`` (dense Cholesky, damping 1e-3, vectorised) on one cost
  ``log(T_target⁻¹ T(q))`` (6 rows, ``th.eb.UrdfRobotModel`` / torchkin FK and body Jacobian, analytic
  Jacobian), in a ``th.TheseusLayer`` with ``backward_mode="implicit"`` (the no-grad iterations, then one
  Gauss–Newton step with the Hessian detached, differentiated by autograd). No joint limits.

Success of both is re-checked with diffkin's float64 FK at 0.1 mm / 1 mrad. ``grad_rel_diff``: the gradient
w.r.t. each target projected onto the tangent space (the 6 directional derivatives ``<G, T ξ̂>`` along the
body twists ξ = e_k), ``‖g_theseus − g_diffkin‖ / ‖g_diffkin‖`` over the targets both solve (global norms;
``grad_rel_diff_median``: per-target median; ``grad_rel_diff_trans``: the 3 translation entries only).
For a redundant arm the two local solvers stop at different points of the self-motion manifold, so the
row ``theseus vs diffkin at theseus's q`` also re-differentiates diffkin warm-started at theseus's solution
(same q, so only the backward rule differs): ``grad_rel_diff_same_q``. ``ratio`` = theseus forward time /
diffkin forward time, ``ratio_backward`` likewise. Rows for theseus's default LM damping 1e-3 and for 1e-9:
the implicit step's Gauss–Newton Cholesky of the rank-6 JᵀJ (7 joints) fails and theseus falls back to the
damped LM step, so its gradient is the damped (JᵀJ + λI)⁻¹Jᵀ rule, which tends to diffkin's J⁺ as λ → 0.

One run (1 thread, 2 shared cores, float64, N = 1000): diffkin forward 0.022 s, backward 0.0039 s,
success 0.994; theseus forward 0.68 s (ratio ≈ 31), backward 0.0089 s, success 0.957 (λ=1e-3) / 0.996
(λ=1e-9); gradient at the same q: rel. diff 0.72 (median 0.10) for λ=1e-3, 6e-5 (median 5e-4) for λ=1e-9;
at each solver's own solution ≈ 1 (median 0.87–0.89): different points of the self-motion manifold.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import torch

from benchmarks.common import print_table, torch_threads
from diffkin import ik, models

__all__ = ["run", "main"]

URDF = Path(__file__).resolve().parents[1] / "diffkin" / "models" / "data" / "panda.urdf"
END_LINK = "panda_link8"


def _hat(xi: torch.Tensor) -> torch.Tensor:
    """(6,) twist (v, ω) -> (4, 4) se(3) matrix."""
    v, w = xi[:3], xi[3:]
    m = xi.new_zeros(4, 4)
    m[0, 1], m[0, 2], m[1, 2] = -w[2], w[1], -w[0]
    m[1, 0], m[2, 0], m[2, 1] = w[2], -w[1], w[0]
    m[:3, 3] = v
    return m


def _tangent(G: torch.Tensor, T: torch.Tensor) -> torch.Tensor:
    """Directional derivatives of the loss along body twists: (N, 6), entry k = <G, T hat(e_k)>."""
    basis = torch.stack([_hat(e) for e in torch.eye(6, dtype=T.dtype)])  # (6, 4, 4)
    dT = T.unsqueeze(1) @ basis  # (N, 6, 4, 4)
    return (G.unsqueeze(1) * dT).sum((-1, -2))


def _success(chain64, q, T):
    with torch.no_grad():
        Tq = chain64.forward_kinematics(q.double())
        T = T.double()
        dp = (Tq[..., :3, 3] - T[..., :3, 3]).norm(dim=-1)
        R = T[..., :3, :3].transpose(-1, -2) @ Tq[..., :3, :3]
        c = ((R.diagonal(dim1=-1, dim2=-2).sum(-1) - 1) / 2).clamp(-1, 1)
        return (dp <= 1e-4) & (torch.arccos(c) <= 1e-3)


def _theseus_layer(N: int, dtype, max_iterations: int):
    import theseus as th

    model = th.eb.UrdfRobotModel(str(URDF), dtype=dtype, link_names=[END_LINK])

    class PoseError(th.CostFunction):
        def __init__(self, q, target, weight, name=None):
            super().__init__(weight, name=name)
            self.q, self.target = q, target
            self.register_optim_vars(["q"])
            self.register_aux_vars(["target"])

        def _pose(self, jac=None):
            return model.forward_kinematics(self.q, jacobians=jac)[END_LINK]

        def error(self):
            return self.target.local(self._pose())

        def jacobians(self):
            jac: dict = {}
            pose = self._pose(jac)
            dlog: list = []
            err = self.target.inverse().compose(pose).log_map(jacobians=dlog)
            return [dlog[0] @ jac[END_LINK]], err

        def dim(self):
            return 6

        def _copy_impl(self, new_name=None):
            return PoseError(self.q.copy(), self.target.copy(), self.weight.copy(), name=new_name)

    q = th.Vector(7, name="q", dtype=dtype)
    target = th.SE3(name="target", dtype=dtype)
    objective = th.Objective(dtype=dtype)
    objective.add(PoseError(q, target, th.ScaleCostWeight(torch.ones(1, dtype=dtype)), name="pose"))
    optimizer = th.LevenbergMarquardt(objective, linear_solver_cls=th.CholeskyDenseSolver,
                                      max_iterations=max_iterations, step_size=1.0, abs_err_tolerance=1e-14,
                                      rel_err_tolerance=1e-12, vectorize=True)
    return th.TheseusLayer(optimizer, vectorize=True)


def _fwd_bwd(forward, backward, repeats):
    """Median forward and backward times; every backward follows its own forward (warm-up pair first)."""
    forward()
    backward()
    tf, tb = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        forward()
        t1 = time.perf_counter()
        backward()
        tf.append(t1 - t0)
        tb.append(time.perf_counter() - t1)
    return statistics.median(tf), statistics.median(tb)


def run(args=None) -> list[dict]:
    args = args if args is not None else parse_args([])
    quick = getattr(args, "quick", False)
    N = getattr(args, "targets", None) or (200 if quick else 1000)
    dtype = {"float32": torch.float32, "float64": torch.float64}[getattr(args, "dtype", None) or "float64"]
    threads = getattr(args, "threads", None) or 1
    iters = getattr(args, "theseus_iterations", None) or 30
    repeats = 1 if quick else 3
    with torch_threads(threads):
        chain = models.load("panda", dtype=dtype).requires_grad_(False)
        chain64 = models.load("panda", dtype=torch.float64).requires_grad_(False)
        g = torch.Generator().manual_seed(0)
        q_true = chain.random_configuration((N,), generator=g)
        q_start = q_true + 0.3 * (2 * torch.rand(q_true.shape, generator=g, dtype=dtype) - 1)
        with torch.no_grad():
            T = chain.forward_kinematics(q_true)

        def loss_of(q):
            return (q - q_true).square().sum()

        # diffkin
        st: dict = {}

        def dk_forward(q0=q_start, st=st):
            Tg = T.clone().requires_grad_(True)
            st["res"], st["T"] = ik.solve(chain, Tg, q0=q0, num_seeds=1), Tg

        def dk_backward(st=st):
            st["T"].grad = None
            loss_of(st["res"].q).backward()

        dk_f, dk_b = _fwd_bwd(dk_forward, dk_backward, repeats)
        q_dk, G_dk = st["res"].q.detach(), st["T"].grad.clone()
        ok_dk = _success(chain64, q_dk, T)

        base = {"benchmark": "ik_theseus", "targets": N, "dtype": str(dtype)[6:], "threads": threads}
        rows = [{**base, "impl": "diffkin ik.solve (LM, 1 seed, implicit J+)",
                 "success": float(ok_dk.float().mean()), "forward_s": dk_f, "backward_s": dk_b, "ratio": 1.0,
                 "grad_rel_diff": 0.0}]
        lim_lo, lim_hi = chain.lower_upper()

        def rel(Ga, Gb, mask):
            ga, gb = _tangent(Ga.double(), T.double())[mask], _tangent(Gb.double(), T.double())[mask]
            if ga.shape[0] == 0:
                return float("nan"), float("nan"), float("nan")
            per = (ga - gb).norm(dim=-1) / gb.norm(dim=-1).clamp_min(1e-300)
            tr = float((ga[:, :3] - gb[:, :3]).norm() / gb[:, :3].norm())
            return float((ga - gb).norm() / gb.norm()), float(per.median()), tr

        import theseus as th

        layer = _theseus_layer(N, dtype, iters)
        for damping in (1e-3, 1e-9):
            ts: dict = {}

            def th_forward(ts=ts, damping=damping):
                Tg = T.clone().requires_grad_(True)
                sol, _ = layer.forward({"target": Tg[:, :3, :], "q": q_start.clone()},
                                       optimizer_kwargs={"backward_mode": "implicit", "damping": damping,
                                                         "track_best_solution": False, "verbose": False})
                ts["q"], ts["T"] = sol["q"], Tg

            def th_backward(ts=ts):
                ts["T"].grad = None
                loss_of(ts["q"]).backward()

            th_f, th_b = _fwd_bwd(th_forward, th_backward, repeats)
            q_th, G_th = ts["q"].detach(), ts["T"].grad.clone()
            ok_th = _success(chain64, q_th, T)
            # diffkin's implicit gradient at theseus's solution (same q: only the backward rule differs)
            st2: dict = {}
            dk_forward(q0=q_th, st=st2)
            dk_backward(st=st2)
            same_q = (st2["res"].q.detach() - q_th).norm(dim=-1) < 1e-5
            both, m2 = ok_dk & ok_th, ok_th & same_q
            r_own, r_same = rel(G_th, G_dk, both), rel(G_th, st2["T"].grad, m2)
            dq = (q_th - q_dk).norm(dim=-1)[both]
            rows.append({
                **base,
                "impl": f"theseus {th.__version__} LM damping {damping:g} (dense Cholesky, {iters} it, "
                        "implicit)",
                "success": float(ok_th.float().mean()), "forward_s": th_f, "backward_s": th_b,
                "ratio": th_f / dk_f, "ratio_backward": th_b / dk_b, "grad_rel_diff": r_own[0],
                "grad_rel_diff_median": r_own[1], "grad_rel_diff_trans": r_own[2],
                "compared": int(both.sum()),
                "median_dq_rad": float(dq.median()) if dq.numel() else float("nan"),
                "in_limits": float(((q_th >= lim_lo) & (q_th <= lim_hi)).all(-1).float().mean()),
                "grad_rel_diff_same_q": r_same[0], "grad_rel_diff_same_q_median": r_same[1],
                "compared_same_q": int(m2.sum())})
    return rows


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--targets", type=int, default=None)
    p.add_argument("--dtype", choices=["float32", "float64"], default=None)
    p.add_argument("--theseus-iterations", type=int, default=None)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--quick", action="store_true")
    return p.parse_args(argv)


def main(argv=None) -> int:
    print_table(run(parse_args(argv)), "IK implicit gradients: diffkin vs theseus")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

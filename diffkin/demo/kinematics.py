"""``diffkin demo`` sections: batch IK, the IK layer, URDF trees, MuJoCo models and the fused kernels."""

from __future__ import annotations

import math
import time
from pathlib import Path

import torch

from ..errors import require
from ._common import Report, _figure, _md_table, _shipped, _timed

__all__ = ["section_ik", "section_ik_layer", "section_trees", "section_mjcf", "section_kernels"]


def _timed_fk(chain, B: int):
    """(the generator (seed 0), B random configurations drawn from it, their FK and its time in s, after a
    warm-up on 64 of them)."""
    g = torch.Generator().manual_seed(0)
    q = chain.random_configuration(B, generator=g)
    with torch.no_grad():
        chain.forward_kinematics(q[:64])
        T, dt = _timed(lambda: chain.forward_kinematics(q))
    return g, q, T, dt


def _pk_ik(T, pos_tol, rot_tol):
    """pytorch-kinematics' batched IK on the same Panda (from diffkin's URDF), float32, with the fastest
    settings of benchmarks/bench_ik.py's sweep (10 retries, 50 iterations, lr 1, early stopping)."""
    import pytorch_kinematics as pk

    urdf = (Path(__file__).parent.parent / "models" / "data" / "panda.urdf").read_bytes()
    pk_chain = pk.build_serial_chain_from_urdf(urdf, "panda_link8").to(dtype=torch.float32)
    lim = torch.as_tensor(pk_chain.get_joint_limits(), dtype=torch.float32).T
    torch.manual_seed(0)
    ik = pk.PseudoInverseIK(
        pk_chain, pos_tolerance=pos_tol, rot_tolerance=rot_tol, num_retries=10, max_iterations=50, lr=1.0,
        joint_limits=lim, early_stopping_any_converged=True, early_stopping_no_improvement="all",
    )  # fmt: skip
    goal = pk.Transform3d(matrix=T.to(torch.float32))
    sol, dt = _timed(lambda: ik.solve(goal))
    # First converged retry (else the first); the caller scores it independently with diffkin's FK.
    conv = sol.converged
    first = torch.where(conv.any(1), conv.float().argmax(1), torch.zeros_like(conv[:, 0], dtype=torch.long))
    return sol.solutions[torch.arange(T.shape[0]), first], dt


def section_ik(report: Report, n_targets: int, n_pk: int) -> None:
    from .. import models
    from ..ik import solve
    from ..ik.result import final_errors

    chain = models.load("panda", dtype=torch.float32)
    g = torch.Generator().manual_seed(0)
    q_true = chain.random_configuration(n_targets, generator=g)
    T = chain.forward_kinematics(q_true).detach()
    pos_tol, rot_tol = 1e-4, 1e-3
    solve(chain, T[:8], seed=1)  # warm-up (allocations, lazy imports)
    res, dt = _timed(
        lambda: solve(chain, T, seed=1, position_tolerance=pos_tol, orientation_tolerance=rot_tol)
    )
    ok = res.success
    within = chain.within_limits(res.q.detach(), tol=1e-6) & ok
    rows = [
        [
            "diffkin `ik.solve`",
            n_targets,
            f"{ok.float().mean() * 100:.2f} %",
            f"{within.float().mean() * 100:.2f} %",
            f"{dt:.2f}",
            f"{n_targets / dt:,.0f}",
        ]
    ]
    ratio = None
    try:
        q_pk, dt_pk = _pk_ik(T[:n_pk], pos_tol, rot_tol)
        chain64 = models.load("panda", dtype=torch.float64)
        perr, rerr = final_errors(chain64, q_pk.double(), T[:n_pk].double(), position_only=False)
        pk_ok = (perr <= pos_tol) & (rerr <= rot_tol)
        pk_within = chain64.within_limits(q_pk.double(), tol=1e-6) & pk_ok
        rows.append(
            [
                "pytorch-kinematics `PseudoInverseIK` (10 retries, lr 1)",
                n_pk,
                f"{pk_ok.double().mean() * 100:.2f} %",
                f"{pk_within.double().mean() * 100:.2f} %",
                f"{dt_pk:.2f}",
                f"{n_pk / dt_pk:,.0f}",
            ]
        )
        ratio = (n_targets / dt) / (n_pk / dt_pk)
    except ImportError:
        rows.append(["pytorch-kinematics", "not installed", "", "", "", ""])
    fig = _figure(figsize=(9, 3.4))
    axs = fig.subplots(1, 2)
    pe = res.position_error.detach().double().clamp_min(1e-12).log10()
    oe = res.orientation_error.detach().double().clamp_min(1e-12).log10()
    axs[0].hist(pe.numpy(), bins=60, color="tab:blue")
    axs[0].axvline(math.log10(pos_tol), color="k", ls="--", label="tolerance 0.1 mm")
    axs[0].set_xlabel("log10 position error [m]")
    axs[1].hist(oe.numpy(), bins=60, color="tab:orange")
    axs[1].axvline(math.log10(rot_tol), color="k", ls="--", label="tolerance 1 mrad")
    axs[1].set_xlabel("log10 orientation error [rad]")
    for ax in axs:
        ax.legend()
        ax.set_ylabel("targets")
    fig.suptitle(f"diffkin IK on {n_targets} random Panda poses")
    fig.tight_layout()
    fig.savefig(report.out / "ik_errors.png", dpi=110)
    body = (
        f"{n_targets} random reachable full-pose Panda targets (FK of uniform joints within limits), "
        "tolerance 0.1 mm and 1 mrad, float32, random seeds, joint limits enforced.\n\n"
        + _md_table(["solver", "targets", "success", "success within limits", "time [s]", "solves/s"], rows)
        + (f"\n\nThroughput ratio diffkin / pytorch-kinematics: **{ratio:.1f}×**." if ratio else "")
        + "\n\n![IK errors](ik_errors.png)\n"
    )
    report.add("Batch IK (Panda)", body)
    if ok.float().mean() < 0.99:
        report.failures.append(f"IK success {ok.float().mean() * 100:.2f} % below 99 %")


def section_ik_layer(report: Report, quick: bool) -> None:
    """IK as a differentiable layer: a UR5's unknown tool frame found by gradient descent through ik.solve."""
    from .. import models
    from ..ik import solve
    from ..rotations import matrix_to_rotvec, rotvec_to_matrix
    from ..transforms import make_transform

    f64 = torch.float64
    g = torch.Generator().manual_seed(0)
    true_tool = make_transform(rotvec_to_matrix(torch.tensor([0.12, -0.17, 0.05], dtype=f64)),
                               torch.tensor([0.04, 0.02, 0.09], dtype=f64))
    real = models.load("ur5", dtype=f64).requires_grad_(False)
    real.tool = true_tool
    n_targets, steps = (32, 120) if quick else (64, 200)
    q_rec = real.random_configuration(n_targets, generator=g)
    with torch.no_grad():
        T_cmd = real.forward_kinematics(q_rec)
    q_rec = q_rec + 1e-4 * torch.randn(q_rec.shape, generator=g, dtype=f64)  # encoder noise
    model = models.load("ur5", dtype=f64).requires_grad_(False)
    model.tool_delta.requires_grad_(True)

    def tool_error() -> tuple[float, float]:
        T = model.tool.detach() if model.tool is not None else torch.eye(4, dtype=f64)
        ang = float(matrix_to_rotvec(T[:3, :3].T @ true_tool[:3, :3]).norm())
        return float((T[:3, 3] - true_tool[:3, 3]).norm()) * 1e3, math.degrees(ang)

    before = tool_error()
    opt = torch.optim.Adam([model.tool_delta], lr=0.01)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps, eta_min=5e-4)
    history = []

    def fit():
        for _ in range(steps):
            res = solve(model, T_cmd, q0=q_rec, num_seeds=1, max_iterations=64, seed=0)
            dq = res.q - q_rec
            dq = torch.atan2(torch.sin(dq), torch.cos(dq))
            loss = (dq[res.success] ** 2).sum(-1).mean()
            opt.zero_grad()
            loss.backward()  # through the IK solution: dq* = −J⁻¹ J_θ dθ (implicit function theorem)
            opt.step()
            sched.step()
            history.append(tool_error()[0])

    _, dt = _timed(fit)
    after = tool_error()
    fig = _figure(figsize=(6, 3.2))
    ax = fig.subplots()
    ax.semilogy(range(1, len(history) + 1), history)
    ax.set_xlabel("gradient step through ik.solve")
    ax.set_ylabel("tool position error [mm]")
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(report.out / "ik_layer_tool.png", dpi=110)
    rows = [["before", f"{before[0]:.2f}", f"{before[1]:.3f}"],
            ["after", f"{after[0]:.3f}", f"{after[1]:.4f}"]]
    body = (
        f"A UR5 carries a tool whose mounting is unknown. Given {n_targets} commanded poses and the "
        "joint readings there (σ = 1e-4 rad), the tool correction `tool_delta` is fitted by Adam on the "
        "joint-space distance between `ik.solve(model, T).q` and the readings — the gradient comes through "
        f"the IK solution by the implicit function theorem. {steps} steps, {dt:.1f} s.\n\n"
        + _md_table(["tool frame", "position error [mm]", "angle error [deg]"], rows)
        + "\n\n![tool error](ik_layer_tool.png)\n"
    )
    report.add("IK as a differentiable layer (tool identification)", body)
    if after[0] > 0.5:
        report.failures.append(f"tool identification through IK left {after[0]:.2f} mm")


def section_trees(report: Report, quick: bool) -> None:
    """A URDF tree as one learnable model: FK, IK and a geometry fit through FK on the Allegro hand."""
    from .. import models
    from ..ik import solve

    tips = [f"link_{i}.0_tip" for i in (3, 7, 11, 15)]
    path = models.model_path("allegro_right_hand")
    hand = models.from_urdf(path, tips, dtype=torch.float64)
    B = 10_000 if quick else 100_000
    g, q, T, dt_fk = _timed_fk(hand, B)
    N = 200 if quick else 1_000
    targets = T[:N, :, :3, 3]  # the four fingertip positions, (N, 4, 3)
    res, dt_ik = _timed(lambda: solve(hand, targets, position_only=True, seed=1))
    # learnable geometry: fit every joint origin (xyz) of a hand whose fingers are 2 mm off, from
    # measured fingertip positions, by L-BFGS through the same FK (gradients w.r.t. URDF origins)
    true = models.from_urdf(path, tips, dtype=torch.float64).requires_grad_(False)
    with torch.no_grad():
        true.origin_xyz.add_(0.002 * torch.randn(true.origin_xyz.shape, generator=g, dtype=torch.float64))
    q_meas = hand.random_configuration(40, generator=g)
    q_test = hand.random_configuration(400, generator=g)
    with torch.no_grad():
        p_meas = true.forward_kinematics(q_meas)[..., :3, 3]
        p_test = true.forward_kinematics(q_test)[..., :3, 3]
    fit = models.from_urdf(path, tips, dtype=torch.float64).requires_grad_(False)
    fit.origin_xyz.requires_grad_(True)

    def held_out_mm() -> float:
        with torch.no_grad():
            err = fit.forward_kinematics(q_test)[..., :3, 3] - p_test
            return float(err.norm(dim=-1).square().mean().sqrt()) * 1e3

    before = held_out_mm()
    opt = torch.optim.LBFGS([fit.origin_xyz], lr=1.0, max_iter=200, line_search_fn="strong_wolfe")

    def closure():
        opt.zero_grad()
        loss = (fit.forward_kinematics(q_meas)[..., :3, 3] - p_meas).square().sum()
        loss.backward()
        return loss

    _, dt_fit = _timed(lambda: opt.step(closure))
    after = held_out_mm()
    rows = [
        ["FK, 4 fingertips in one pass", f"{B:,} configurations", "", f"{dt_fk:.3f}", f"{B / dt_fk:,.0f} /s"],
        ["IK, 4 fingertip positions at once (0.1 mm)", f"{N} targets",
         f"{res.success.float().mean() * 100:.1f} %", f"{dt_ik:.2f}", f"{N / dt_ik:,.0f} /s"],
        ["fit of all joint origins (L-BFGS through FK)", "40 measured poses",
         f"{before:.3f} → {after:.4f} mm RMS", f"{dt_fit:.2f}", ""],
    ]
    body = (
        f"`models.from_urdf(allegro_right_hand.urdf, [4 fingertip links])`: one kinematic tree, "
        f"{hand.n_joints} joints, FK `{tuple(T.shape[1:])}` per configuration, Jacobian "
        f"`({hand.n_ends}, 6, {hand.n_joints})`, float64. Every joint origin and axis is an `nn.Parameter`; "
        "the last row fits the origins of a hand whose joints are 2 mm off from fingertip positions "
        "(held-out RMS over 400 poses), and `chain.to_urdf(path)` would write the fitted file.\n\n"
        + _md_table(["what", "size", "result", "time [s]", "rate"], rows)
    )
    report.add("URDF trees and learnable geometry (Allegro hand)", body)
    if res.success.float().mean() < 0.99:
        report.failures.append(f"tree IK success {res.success.float().mean() * 100:.1f} % below 99 %")
    if after > 0.01:
        report.failures.append(f"URDF geometry fit left {after:.3f} mm RMS")


def section_mjcf(report: Report, quick: bool) -> None:
    """A MuJoCo Menagerie humanoid (floating base): FK of every body against MuJoCo, whole-body IK."""
    path = _shipped("unitree_g1")
    try:
        mujoco = require("mujoco", "mjcf", "MuJoCo models")
    except ImportError as exc:
        report.add("MuJoCo models (Menagerie G1, floating base)", f"Skipped: {exc}")
        return
    if not path.is_file():
        report.add("MuJoCo models (Menagerie G1, floating base)", f"Skipped: {path} is not installed.")
        return
    from .. import models
    from ..ik import solve
    from ..models.mjcf import compile_mjcf

    m = compile_mjcf(path)[0]
    bodies = [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, i) for i in range(1, m.nbody)]
    chain = models.from_mjcf(path, bodies, dtype=torch.float64).requires_grad_(False)
    B = 5_000 if quick else 50_000
    g, q, T, dt_fk = _timed_fk(chain, B)
    d = mujoco.MjData(m)
    worst, rows_mj = 0.0, 200
    t0 = time.perf_counter()
    for qpos, Tq in zip(chain.to_qpos(q[:rows_mj]).numpy(), T[:rows_mj].numpy()):
        d.qpos[:] = qpos
        mujoco.mj_kinematics(m, d)
        worst = max(worst, float(abs(d.xpos[1:] - Tq[:, :3, 3]).max()),
                    float(abs(d.xmat[1:].reshape(-1, 3, 3) - Tq[:, :3, :3]).max()))
    dt_mj = (time.perf_counter() - t0) / rows_mj
    ends = ["left_ankle_roll_link", "right_ankle_roll_link", "left_elbow_roll_link", "right_elbow_roll_link"]
    body = models.from_mjcf(path, ends, dtype=torch.float64).requires_grad_(False)
    N = 20 if quick else 100
    with torch.no_grad():
        targets = body.forward_kinematics(body.random_configuration(N, generator=g))
    res, dt_ik = _timed(lambda: solve(body, targets, seed=0, num_seeds=256, max_iterations=48))
    rows = [
        [f"FK, all {len(bodies)} bodies", f"{B:,} configurations",
         f"max abs difference from mj_kinematics {worst:.1e}",
         f"{dt_fk:.3f}", f"{1e6 * dt_fk / B:.1f} µs/row (MuJoCo loop: {1e6 * dt_mj:.1f})"],
        ["whole-body IK: 2 feet + 2 hands (poses), floating base", f"{N} targets",
         f"{res.success.float().mean() * 100:.1f} %", f"{dt_ik:.2f}", f"{N / dt_ik:,.1f} /s"],
    ]
    text = (
        f"`models.from_mjcf(\"unitree_g1/g1.xml\", bodies)`: MuJoCo Menagerie's G1 read by MuJoCo's own "
        f"compiler (meshes absent), a free joint and {chain.nv - 6} hinges: q `(..., {chain.nq})` in "
        f"MuJoCo's qpos order (position, unit quaternion, joints), Jacobian columns `(..., {chain.nv})`. "
        "IK moves the "
        "base on SE(3) (quaternion steps q ⊗ exp(ω/2)), 0.1 mm / 1 mrad at all four end links.\n\n"
        + _md_table(["what", "size", "result", "time [s]", "rate"], rows)
    )
    report.add("MuJoCo models (Menagerie G1, floating base)", text)
    if worst > 1e-9:
        report.failures.append(f"MJCF FK differs from MuJoCo by {worst:.2e}")
    if res.success.float().mean() < 0.9:
        report.failures.append(f"whole-body IK success {res.success.float().mean() * 100:.1f} % below 90 %")


def _best_of(fn, repeats: int) -> float:
    fn()
    return min(_timed(fn)[1] for _ in range(repeats))


def section_kernels(report: Report, quick: bool) -> None:
    """The fused native kernel against the torch kernels it stands in for: speed and equality."""
    from .. import models
    from ..kernels import native

    if not native.available():
        report.add("Fused FK + Jacobian kernel", "No C compiler was found: every call used the torch kernels "
                   "(`python -m diffkin.kernels` says why).")
        return
    chain = models.load("panda", dtype=torch.float32)
    B = 20_000 if quick else 100_000
    q = chain.random_configuration(B, generator=torch.Generator().manual_seed(0))
    q1 = q[:1]
    rows, worst = [], 0.0
    with torch.no_grad():
        for what, size, x, reps, fn in (
            ("FK", f"{B:,}", q, 5, chain.forward_kinematics),
            ("FK + Jacobian", f"{B:,}", q, 5, chain.forward_kinematics_and_jacobian),
            ("FK", "1", q1, 200, chain.forward_kinematics),
            ("FK + Jacobian", "1", q1, 200, chain.forward_kinematics_and_jacobian),
        ):
            t_native = _best_of(lambda: fn(x), reps)  # noqa: B023  (called within this iteration)
            out = fn(x)
            with native.disabled():
                t_torch = _best_of(lambda: fn(x), reps)  # noqa: B023
                ref = fn(x)
            outs, refs = (out, ref) if isinstance(out, tuple) else ((out,), (ref,))
            worst = max(worst, max(float((a - b).abs().max()) for a, b in zip(outs, refs)))
            n = x.shape[0]
            rows.append([what, size, f"{t_torch * 1e6:,.0f} µs", f"{t_native * 1e6:,.0f} µs",
                         f"{t_torch / t_native:.1f}×", f"{n / t_native / 1e6:.2f} M/s" if n > 1 else ""])
    body = (
        f"`chain.forward_kinematics` and `chain.forward_kinematics_and_jacobian` on CPU without autograd run "
        f"one fused C pass (`diffkin.kernels.native`, built on first use) instead of the torch kernels; with "
        f"autograd, on CUDA, or under `torch.compile` / `torch.func` the torch kernels run. Panda, float32, "
        f"{torch.get_num_threads()} thread(s), best of several calls; largest difference between the two "
        f"over every output: {worst:.1e}.\n\n"
        + _md_table(["what", "batch", "torch kernels", "fused kernel", "speed-up", "rate"], rows)
    )
    report.add("Fused FK + Jacobian kernel", body)
    if worst > 1e-5:
        report.failures.append(f"fused kernel differs from the torch kernels by {worst:.1e}")

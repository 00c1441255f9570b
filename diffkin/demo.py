"""``diffkin demo``: the tour of what diffkin does, written as a report (Markdown + PNG) under ``runs/``.

Sections: batch IK on Panda targets (against pytorch-kinematics in the same run), URDF trees, a MuJoCo
Menagerie humanoid with a floating base (FK against MuJoCo, whole-body IK), calibration before/after,
calibration from camera images beside OpenCV's hand-eye methods,
the §3.7.5 CLIK comparison, human motion retargeted onto the G1, and a short PPO run on the batched Reach
environment (``training.train``, called in-process when the ``rl`` extra and the repository's ``configs/``
are there; otherwise the section says why it was skipped).

:func:`run_demo` leaves torch's thread count and matplotlib's backend alone (figures are drawn on
:class:`matplotlib.figure.Figure` objects); ``diffkin demo`` runs it on one torch thread unless given
``--threads N``.
"""

from __future__ import annotations

import json
import math
import statistics
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path

import torch

from .errors import require

__all__ = ["run_demo"]

REPO_ROOT = Path(__file__).resolve().parent.parent
_NOT_SHIPPED = ("{} is not in the installed package (its licence is not stated: the robot ships in the "
                "source repository only).")


def _shipped(name: str) -> Path:
    """The file of a catalogued robot (``models.model_path``): the demo reads what the package installs."""
    from .models import model_path

    return model_path(name)


@dataclass
class Report:
    out: Path
    sections: list[str] = field(default_factory=list)
    failures: list[str] = field(default_factory=list)

    def add(self, title: str, body: str) -> None:
        self.sections.append(f"## {title}\n\n{body.strip()}\n")

    def write(self) -> Path:
        head = f"# diffkin demo report\n\nGenerated {time.strftime('%Y-%m-%d %H:%M:%S')} on {_machine()}.\n"
        path = self.out / "report.md"
        path.write_text(head + "\n" + "\n".join(self.sections))
        return path


def _machine() -> str:
    import platform

    threads = torch.get_num_threads()
    cpu = platform.processor() or platform.machine()
    return (
        f"{cpu} CPU, {threads} torch thread(s) (`diffkin demo` uses 1 unless given `--threads N`), "
        f"torch {torch.__version__}"
    )


def _figure_module():
    return require("matplotlib.figure", "plot", "diffkin demo (its figures)")


def _figure(**kwargs):
    """A figure for file output: no pyplot, no backend switch."""
    return _figure_module().Figure(**kwargs)


def _md_table(header: list[str], rows: list[list]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(lines)


def _timed(fn):
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0


def _timed_fk(chain, B: int):
    """(the generator (seed 0), B random configurations drawn from it, their FK and its time in s, after a
    warm-up on 64 of them)."""
    g = torch.Generator().manual_seed(0)
    q = chain.random_configuration(B, generator=g)
    with torch.no_grad():
        chain.forward_kinematics(q[:64])
        T, dt = _timed(lambda: chain.forward_kinematics(q))
    return g, q, T, dt


# ------------------------------------------------------------------------------------------------- IK
def _pk_ik(T, pos_tol, rot_tol):
    """pytorch-kinematics' batched IK on the same Panda (from diffkin's URDF), float32, with the fastest
    settings of benchmarks/bench_ik.py's sweep (10 retries, 50 iterations, lr 1, early stopping)."""
    import pytorch_kinematics as pk

    urdf = (Path(__file__).parent / "models" / "data" / "panda.urdf").read_bytes()
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
    from . import models
    from .ik import solve
    from .ik.result import final_errors

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


# --------------------------------------------------------------------------------------- IK layer
def section_ik_layer(report: Report, quick: bool) -> None:
    """IK as a differentiable layer: a UR5's unknown tool frame found by gradient descent through ik.solve."""
    from . import models
    from .ik import solve
    from .rotations import matrix_to_rotvec, rotvec_to_matrix
    from .transforms import make_transform

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


# ------------------------------------------------------------------------------------- URDF trees
def section_trees(report: Report, quick: bool) -> None:
    """A URDF tree as one learnable model: FK, IK and a geometry fit through FK on the Allegro hand."""
    from . import models
    from .ik import solve

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


# ----------------------------------------------------------------------------------------- MuJoCo
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
    from . import models
    from .ik import solve
    from .models.mjcf import compile_mjcf

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


# ------------------------------------------------------------------------------------------ kernels
def _best_of(fn, repeats: int) -> float:
    fn()
    return min(_timed(fn)[1] for _ in range(repeats))


def section_kernels(report: Report, quick: bool) -> None:
    """The fused native kernel against the torch kernels it stands in for: speed and equality."""
    from . import models
    from .kernels import native

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


# ---------------------------------------------------------------------------------------- calibration
def section_calibration(report: Report, n_poses: int) -> None:
    from . import models
    from .calibration import calibrate, validation_error

    nominal = models.load("panda", dtype=torch.float64)
    g = torch.Generator().manual_seed(7)
    true = nominal.copy()
    with torch.no_grad():
        n = nominal.n_joints
        true.a.add_((torch.rand(n, generator=g, dtype=torch.float64) * 2 - 1) * 2e-3)
        true.d.add_((torch.rand(n, generator=g, dtype=torch.float64) * 2 - 1) * 2e-3)
        true.alpha.add_((torch.rand(n, generator=g, dtype=torch.float64) * 2 - 1) * math.radians(0.2))
        true.theta.add_((torch.rand(n, generator=g, dtype=torch.float64) * 2 - 1) * math.radians(0.2))
    q = nominal.random_configuration(n_poses + 100, generator=g)
    T_true = true.forward_kinematics(q).detach()
    T = T_true.clone()
    T[:, :3, 3] += 5e-5 * torch.randn(q.shape[0], 3, generator=g, dtype=torch.float64)
    # Fit on noisy measurements; validate against the true poses so the figure is the model error, not noise.
    q_fit, T_fit, q_val, T_val = q[:n_poses], T[:n_poses], q[n_poses:], T_true[n_poses:]
    before = validation_error(nominal, q_val, T_val)
    rows = [
        ["nominal", "-", f"{before['position_rms'] * 1e3:.3f}", f"{before['position_max'] * 1e3:.3f}", "-"]
    ]
    results = {}
    for method in ("least_squares", "gradient"):
        res, dt = _timed(lambda m=method: calibrate(nominal, q_fit, T_fit, method=m, progress=False))
        after = validation_error(res.chain, q_val, T_val)
        results[method] = res
        rows.append(
            [
                method,
                f"{dt:.2f}",
                f"{after['position_rms'] * 1e3:.4f}",
                f"{after['position_max'] * 1e3:.4f}",
                len(res.report.unidentifiable),
            ]
        )
    results["least_squares"].plot_residuals(report.out / "calibration_residuals.png")
    body = (
        f"A simulated Panda whose DH table differs from nominal by up to ±2 mm and ±0.2° per parameter; "
        f"{n_poses} measured poses with 0.05 mm position noise; validation on 100 held-out poses "
        "(true, noise-free).\n\n"
        + _md_table(
            [
                "model",
                "fit time [s]",
                "validation RMS [mm]",
                "validation max [mm]",
                "parameters fixed (unidentifiable)",
            ],
            rows,
        )
        + "\n\n![calibration residuals](calibration_residuals.png)\n"
    )
    report.add("Calibration (§2.11)", body)


# --------------------------------------------------------------------------------- camera calibration
def section_camera_calibration(report: Report, quick: bool) -> None:
    """``calibrate_camera`` on the synthetic Panda scene of ``benchmarks/camera_scenes.py`` (a board on the
    flange, a fixed camera, the robot's geometry off by up to ±1 mm / ±0.1°, 0.3 px noise) beside OpenCV's
    seven hand-eye methods on the same pixels; needs the ``camera`` extra and the repository's benchmarks/."""
    import importlib.util
    import warnings

    title = "Camera calibration (issue 38)"
    path = REPO_ROOT / "benchmarks" / "camera_scenes.py"
    if importlib.util.find_spec("cv2") is None or not path.exists():
        why = "OpenCV (the `camera` extra)" if importlib.util.find_spec("cv2") is None else str(path)
        report.add(title, f"Skipped: needs {why}.")
        return
    from .calibration import calibrate_camera

    spec = importlib.util.spec_from_file_location("diffkin_demo_camera_scenes", path)
    scenes = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(scenes)
    n_images, sigma = (20, 0.3) if quick else (30, 0.3)
    nominal, true, q, q_out, cam, board, _ = scenes.scene("panda", n_images)
    uv = scenes.images(true, q, cam, board, "eye_to_hand", sigma)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res, dt = _timed(lambda: calibrate_camera(
            nominal, q, uv, scenes.chessboard(), camera_matrix=scenes.K, dist_coeffs=scenes.DIST,
            measurement_noise=sigma, cross_validation=0, progress=False))
    rows, errors = [], {}

    def row(name, X, Y, chain):
        mm = float((X[:3, 3] - cam[:3, 3]).norm()) * 1e3
        held = scenes.held_out_3d(chain, X, Y, true, cam, board, q_out, "eye_to_hand") * 1e3
        errors[name] = mm
        rows.append([name, f"{mm:.3f}", f"{held:.3f}"])

    row("diffkin calibrate_camera", res.camera_pose, res.board_pose, res.chain)
    for name, (X, Y) in scenes.opencv_pipelines(nominal, q, uv, "eye_to_hand").items():
        row(f"OpenCV {name}", X, Y, nominal)
    best = min((v, k) for k, v in errors.items() if k.startswith("OpenCV"))
    ratio = best[0] / errors["diffkin calibrate_camera"]
    res.plot_residuals(report.out / "camera_calibration_residuals.png")
    body = (
        f"A Panda (its URDF) with a chessboard on its flange, seen by a fixed camera in {n_images} postures "
        f"with {sigma} px of noise; its geometry off by up to ±1 mm / ±0.1°. `calibrate_camera` fits robot, "
        f"camera and board in {dt:.1f} s (reprojection RMS {res.initial_reprojection_rms:.2f} -> "
        f"{res.reprojection_rms:.3f} px, noise ratio {res.noise_ratio:.2f}); OpenCV's methods trust the "
        f"nominal kinematics. Camera position error: {ratio:.1f}x closer than OpenCV's best ({best[1]}).\n\n"
        + _md_table(["method", "camera error [mm]", "board corners at 100 held-out postures, RMS [mm]"], rows)
        + "\n\n![reprojection per image before and after](camera_calibration_residuals.png)\n"
    )
    report.add(title, body)
    if ratio < 5.0:
        report.failures.append(f"calibrate_camera only {ratio:.1f}x closer than OpenCV's best (5x expected)")


# ----------------------------------------------------------------------------------------------- CLIK
def _book_circle(t_end: float, dt: float):
    """§3.7.5 target: p_d(t) on a circle of radius 0.25 m centred at (0.25, 0.5) m, one turn every 2 s
    for 4 s, then at rest; φ_d(t) = sin(πt/24). Returns ``(x_d, ẋ_d)`` ``(S, 6)`` as [p; RPY angles]."""
    from .trajectories import Trajectory, cartesian_trajectory, circle_path

    t = torch.arange(round(t_end / dt) + 1, dtype=torch.float64) * dt
    speed = 0.25 * math.pi
    moving = t < 4.0
    s = speed * t.clamp(max=4.0)
    timing = Trajectory(s, torch.where(moving, torch.full_like(t, speed), 0.0), torch.zeros_like(t))
    centre = torch.tensor([0.25, 0.5, 0.0], dtype=torch.float64)
    start = torch.tensor([0.0, 0.5, 0.0], dtype=torch.float64)
    axis = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)
    p, v, _ = cartesian_trajectory(lambda u: circle_path(centre, axis, start, u), timing)
    tc = t.clamp(max=4.0)
    phi = torch.sin(math.pi / 24 * tc)
    dphi = torch.where(moving, math.pi / 24 * torch.cos(math.pi / 24 * tc), 0.0)
    zero = torch.zeros_like(t)
    x = torch.cat([p, torch.stack([phi, zero, zero], -1)], -1)
    xd = torch.cat([v, torch.stack([dphi, zero, zero], -1)], -1)
    return x, xd


def section_clik(report: Report, quick: bool) -> None:
    from . import models
    from .ik import clik

    chain = models.load("three_link_planar", dtype=torch.float64)
    q0 = torch.tensor([math.pi, -math.pi / 2, -math.pi / 2], dtype=torch.float64)
    dt, t_end = 1e-3, 4.0 if quick else 5.0
    x, xd = _book_circle(t_end, dt)
    steps = x.shape[0] - 1
    full = dict(orientation="euler", convention="RPY", rows=(0, 1, 3))
    pos = dict(orientation=None, rows=(0, 1))
    runs = {
        "open loop (3.47)": (dict(algorithm="inverse", K=0.0, **full), (x, xd)),
        "Jacobian inverse (3.70), K = diag(500, 500, 100)": (
            dict(algorithm="inverse", K=[500.0, 500.0, 100.0], **full),
            (x, xd),
        ),
        "pseudo-inverse (3.72), position only": (dict(algorithm="pseudo_inverse", K=500.0, **pos), (x, xd)),
        "transpose (3.76), position only": (dict(algorithm="transpose", K=500.0, **pos), (x, xd)),
        "pseudo-inverse + manipulability null space (k0 = 50)": (
            dict(algorithm="pseudo_inverse", K=500.0, nullspace="manipulability", k0=50.0, **pos),
            (x, xd),
        ),
    }
    fig = _figure(figsize=(7.5, 3.8))
    ax = fig.subplots()
    rows = []
    for name, (kw, target) in runs.items():
        res = clik(chain, target, q0, dt, steps, **kw)
        err = res.position_error.detach()
        t = res.t.detach()
        ax.semilogy(t.numpy(), err.clamp_min(1e-16).numpy(), label=name)
        rows.append([name, f"{err[-1]:.2e}", f"{err.max():.2e}"])
    ax.set_xlabel("t [s]")
    ax.set_ylabel("position error norm [m]")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(report.out / "clik_errors.png", dpi=110)
    body = (
        "The textbook's §3.7.5 experiment: three-link planar arm (a = 0.5 m), tip tracking a circle of "
        "radius 0.25 m (one turn every 2 s for 4 s), Δt = 1 ms, forward Euler. The open loop drifts; the "
        "closed-loop schemes hold the error near 1e-5 m and drive it to zero once the target stops.\n\n"
        + _md_table(["algorithm", "final position error [m]", "max position error [m]"], rows)
        + "\n\n![CLIK errors](clik_errors.png)\n"
    )
    report.add("CLIK comparison (§3.7.5)", body)


# ------------------------------------------------------------------------------------ collision-free IK
def section_collision_ik(report: Report, quick: bool) -> None:
    """ik.solve with and without collision=, world= on the FR3 among spheres (a few seconds)."""
    import warnings

    from . import models
    from .collision import RobotCollision, World
    from .ik import solve

    urdf = _shipped("fr3")
    if not urdf.exists():
        report.add("Collision-free IK", f"Skipped: {_NOT_SHIPPED.format(urdf)}")
        return
    chain = models.from_urdf(urdf, "fr3_link8").requires_grad_(False)
    srdf = '<robot><disable_collisions link1="fr3_link1_sc" link2="fr3_link3_sc" reason="Default"/></robot>'
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the FR3's meshes are not shipped: Franka's primitives remain
        rc = RobotCollision.from_urdf(urdf, chain, srdf=srdf).requires_grad_(False)
    world = World(spheres=torch.tensor([[0.45, 0.25, 0.45, 0.10], [0.40, -0.30, 0.70, 0.08],
                                        [0.55, 0.0, 0.15, 0.08]]))
    n = 100 if quick else 200
    with torch.no_grad():
        q = chain.random_configuration((4 * n,), generator=torch.Generator().manual_seed(0))
        q = q[rc.min_distance(q, world) >= 0.01][:n]  # reachable targets with a collision-free solution
        T = chain.forward_kinematics(q)
    solve(chain, T[:4], seed=0)  # warm-up: the fused C pass is built on first use
    rows = []
    for name, kw in (("ik.solve", {}), ("ik.solve(collision=, world=)", {"collision": rc, "world": world})):
        res, dt = _timed(lambda kw=kw: solve(chain, T, seed=0, **kw))
        with torch.no_grad():
            free = (rc.min_distance(res.q, world) >= 0.0) & res.success
        rows.append([name, f"{res.success.float().mean():.1%}", f"{free.float().mean():.1%}",
                     f"{T.shape[0] / dt:.0f}"])
    body = (f"{T.shape[0]} FR3 targets (FK of random configurations clear of collision by 1 cm) among three "
            "spheres, 0.1 mm / 1 mrad. The plain solve reaches them, some with the arm through an "
            "obstacle or itself; with `collision=` success also means every checked distance >= 0.\n\n"
            + _md_table(["solver", "success", "success and collision-free", "solves/s"], rows))
    report.add("Collision-free IK", body)


# ------------------------------------------------------------------------------------------------- RL
def section_rl(report: Report, seconds: int) -> None:
    import yaml

    cfg_path = REPO_ROOT / "configs" / "ppo.yaml"
    if not cfg_path.exists():
        report.add("RL (PPO on batched Reach)", "Skipped: run from a clone of the diffkin repository.")
        return
    try:
        from diffkin.training.config import load_config, read_entry
        from diffkin.training.train import train
    except ImportError as exc:
        report.add(
            "RL (PPO on batched Reach)",
            f"Skipped: the training code is not importable ({exc}); install the `rl` extra "
            "(`pip install -e '.[rl]'`) and run from a clone of the diffkin repository.",
        )
        return
    cfg = read_entry(cfg_path, env="diffkin/Reach-v0", variant="cartesian")  # PPO, Cartesian actions
    cfg["max_wall_seconds"] = seconds
    cfg["eval_freq"] = min(int(cfg.get("eval_freq", 100_000)), 50_000)
    run_dir = report.out / "rl"
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "demo_config.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    try:
        train(load_config(run_dir / "demo_config.yaml"), run_dir, progress_bar=False, log=lambda line: None)
    except Exception:  # the report records the failure and the tour goes on
        report.failures.append("RL training failed: " + traceback.format_exc()[-2000:])
        report.add("RL (PPO on batched Reach)", "Training failed; see the console output.")
        return
    res = json.loads((run_dir / "results.json").read_text())
    final = res["final"]
    fig = _figure(figsize=(6, 3.4))
    ax = fig.subplots()
    xs = [p["wall_s"] for p in res["curve"]]
    ys = [p.get("success_rate", 0) * 100 for p in res["curve"]]
    ax.plot(xs, ys, marker="o")
    ax.set_xlabel("wall-clock [s]")
    ax.set_ylabel("success rate [%]")
    ax.set_ylim(0, 100)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(report.out / "rl_curve.png", dpi=110)
    body = (
        f"PPO on `diffkin/Reach-v0` (Panda, {cfg['n_envs']} torch-batched envs, Cartesian actions), "
        f"{seconds} s wall-clock budget on this machine.\n\n"
        + _md_table(
            ["timesteps", "train time [s]", "success rate (sparse, 0.05 m)", "scripted IK baseline"],
            [
                [
                    res["timesteps"],
                    res["train_wall_s"],
                    f"{final.get('success_rate', 0) * 100:.1f} %",
                    f"{res['scripted_ik'].get('success_rate', 0) * 100:.1f} %",
                ]
            ],
        )
        + "\n\n![learning curve](rl_curve.png)\n"
    )
    report.add("RL (PPO on batched Reach)", body)


def section_teleop(report: Report, quick: bool) -> None:
    """Differential IK at 500 Hz (issue 35): the Panda's hand on a moving circle, ik.solve_velocity with
    mink's tasks and limits (served by one C call a step), beside mink in the same run when installed."""
    title = "Teleoperation rate (differential IK, 500 Hz)"
    path = _shipped("franka_emika_panda")
    try:
        require("mujoco", "mjcf", "MuJoCo models")
    except ImportError as exc:
        report.add(title, f"Skipped: {exc}")
        return
    if not path.is_file():
        report.add(title, f"Skipped: {path} is not installed.")
        return
    import numpy as np

    from . import ik
    from .models import from_mjcf

    chain = from_mjcf(path, "hand", dtype=torch.float64).requires_grad_(False)
    dt, steps = 0.002, 500 if quick else 1500
    q = torch.tensor([0.0, -0.4, 0.0, -2.2, 0.0, 1.9, 0.8], dtype=torch.float64)
    T0 = chain.forward_kinematics(q)
    lo, hi = chain.q_limits[:, 0], chain.q_limits[:, 1]
    targets = T0.expand(steps, 4, 4).clone()
    t = torch.arange(1, steps + 1, dtype=torch.float64) * dt
    targets[:, 1, 3] += 0.05 * torch.sin(math.pi * t)
    targets[:, 2, 3] += 0.05 * (1 - torch.cos(math.pi * t))
    posture = ik.PostureTask(q.clone(), cost=1e-2)
    limits = (ik.ConfigurationLimit(gain=0.95), ik.VelocityLimit(2.0))
    times, margin, speed = [], math.inf, 0.0
    with torch.no_grad():
        for k in range(steps):
            t0 = time.perf_counter_ns()
            task = ik.FrameTask(0, target=targets[k], lm_damping=1e-3)
            v = ik.solve_velocity(chain, q, [task, posture], dt, limits=limits)
            times.append((time.perf_counter_ns() - t0) / 1e3)
            q = q + v * dt  # the Panda's joints are hinges: q ⊕ v is the sum
            margin = min(margin, float(torch.minimum(q - lo, hi - q).min()))
            speed = max(speed, float(v.abs().max()))
        err = float((chain.forward_kinematics(q)[:3, 3] - targets[-1, :3, 3]).norm())
    ours = statistics.median(times)
    rows = [["diffkin ik.solve_velocity (C step)", f"{ours:.1f}", f"{np.percentile(times, 99):.1f}", "1.0"]]
    try:
        import mink

        from .models.mjcf import compile_mjcf

        model = compile_mjcf(path)[0]
        cfg = mink.Configuration(model)
        qm = np.zeros(model.nq)
        qm[:7] = [0.0, -0.4, 0.0, -2.2, 0.0, 1.9, 0.8]
        cfg.update(qm)
        frame = mink.FrameTask("hand", "body", position_cost=1.0, orientation_cost=1.0, lm_damping=1e-3)
        post = mink.PostureTask(model, cost=1e-2)
        post.set_target(qm)
        arm = [model.joint(i).name for i in range(7)]
        lims = [mink.ConfigurationLimit(model, gain=0.95),
                mink.VelocityLimit(model, dict.fromkeys(arm, 2.0))]
        mt = []
        for k in range(min(steps, 300)):
            t0 = time.perf_counter_ns()
            frame.set_target(mink.SE3.from_matrix(targets[k].numpy()))
            cfg.integrate_inplace(mink.solve_ik(cfg, [frame, post], dt, "daqp", limits=lims), dt)
            mt.append((time.perf_counter_ns() - t0) / 1e3)
        theirs = statistics.median(mt)
        rows.append(["mink solve_ik (daqp) + integrate", f"{theirs:.1f}", f"{np.percentile(mt, 99):.1f}",
                     f"{theirs / ours:.1f}"])
    except ImportError:
        rows.append(["mink", "not installed", "", ""])
    body = (
        f"The Menagerie Panda's hand follows a 5 cm circle at 0.5 Hz, Δt = 2 ms, {steps} ticks: a FrameTask "
        "(lm_damping 1e-3), a PostureTask (cost 1e-2), ConfigurationLimit (gain 0.95) and |q̇| ≤ 2 rad/s, in "
        "mink's semantics; on the CPU without autograd each `ik.solve_velocity` is one C call (FK, Jacobian, "
        "mink's SE(3) error and log Jacobian, the box QP solved exactly). Times per step (µs, this "
        "machine, possibly shared: the ratio is from the same run). Worst joint-limit margin "
        f"{margin:.3f} rad (never negative), largest |q̇| {speed:.2f} rad/s (limit 2), final tracking error "
        f"{1e3 * err:.2f} mm. "
        "`examples/teleop.py` runs the same loop with the G1 (feet held, hands moving); "
        "`python -m benchmarks.run teleop` compares PlaCo, mink and pink.\n\n"
        + _md_table(["solver", "median µs", "p99 µs", "× diffkin"], rows)
    )
    if margin < -1e-9 or speed > 2.0 + 1e-9:
        report.failures.append("teleop: a joint limit was violated")
    report.add(title, body)


def section_retarget(report: Report, quick: bool) -> None:
    """Human motion onto the G1 (issue 37): the shipped CMU walk through retarget.clip, the artefact
    metrics of the frame-by-frame warm start and of the whole-clip optimisation, a frame of the clip beside
    the robot, the sole heights."""
    title = "Human motion onto a humanoid (retargeting)"
    urdf = _shipped("g1_urdf")
    if not urdf.is_file():
        report.add(title, f"Skipped: {urdf} is not installed.")
        return
    from . import models, retarget

    mapping = retarget.Mapping.builtin("g1")
    g1 = models.from_urdf(urdf, mapping.frames, floating_base=True, dtype=torch.float64).requires_grad_(False)
    frames = 60 if quick else 150
    walk = retarget.load_bvh(retarget.example_clips()["walk"]).frames_slice(0, frames)
    r, dt = _timed(lambda: retarget.clip(g1, walk, mapping))
    rows = []
    for name, m in (("frame by frame (ik.solve)", r.warm_start), ("whole clip", r.metrics)):
        rows.append([name, int(m.joint_limit_violations[0]), f"{float(m.foot_skating[0]):.1f}",
                     f"{float(m.ground_penetration[0]):.2f}", f"{float(m.floating[0]):.1f}",
                     f"{float(m.keypoint_error[0]):.0f}"])
    fig = _figure(figsize=(7, 3.2))
    ax = fig.subplots()
    t = torch.arange(frames, dtype=torch.float64) / walk.fps
    ends = list(g1.end_links)
    for k, (foot, colour) in enumerate(zip(mapping.feet, ("tab:blue", "tab:orange"))):
        sole = retarget.sole_of(g1, foot)
        with torch.no_grad():
            T = g1.forward_kinematics(r.q[0])[:, ends.index(foot)]
        h = sole.lowest(T)[0] * 1000
        ax.plot(t, h, color=colour, label=f"{foot.split('_')[0]} sole")
        c = r.contacts[0, :, k]
        ax.fill_between(t, -40 - 30 * k, -20 - 30 * k, where=c.numpy(), color=colour, alpha=0.6, step="mid")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("lowest sole point [mm]")
    ax.legend(loc="upper right")
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    fig.savefig(report.out / "retarget_soles.png", dpi=110)
    shown = frames * 3 // 10  # a frame of the walk's stride
    retarget.plot_frame(g1, r, walk, shown, path=report.out / "retarget_frame.png",
                        title=f"the walk, frame {shown}: the clip's skeleton beside the G1")
    body = (
        f"{frames} frames of the shipped CMU walk (60 fps) onto the 29-DoF G1 with the built-in mapping: a "
        f"per-clip scale ({float(r.scale[0]):.3f}), a frame-by-frame warm start with `ik.solve`, then one "
        "Levenberg–Marquardt optimisation over all frames (feet on the ground without sliding while in "
        f"contact, no penetration, joint limits, smoothness; a block-banded solve). {dt:.1f} s in all "
        f"({frames / dt:.0f} frames/s on this machine). Metrics per `retarget.metrics` (mm):\n\n"
        + _md_table(["stage", "limit violations", "skating", "penetration", "floating", "keypoint error"],
                    rows)
        + f"\n\nFrame {shown} (`retarget.plot_frame`): the human skeleton of the clip (blue) beside the G1 "
        "(orange) and the scaled human joints it tracks (green):\n\n"
        "![a retargeted frame](retarget_frame.png)\n\nThe lowest sole point of each foot after the "
        "optimisation (bars: contact detected in the human clip):\n\n![sole heights](retarget_soles.png)\n"
    )
    report.add(title, body)
    m = r.metrics
    if int(m.joint_limit_violations[0]) or float(m.ground_penetration[0]) > 1.0 or float(
            m.foot_skating[0]) > float(r.warm_start.foot_skating[0]):
        report.failures.append("retargeting: the whole-clip result violates a limit, penetrates or skates")


def section_motion(report: Report, quick: bool) -> None:
    """One planned motion (issue 36): motion.plan on the FR3 around a sphere above a table, its timing
    against the limits and a plot of q, q̇, q̈ with them (`diffkin plan` writes the same)."""
    import warnings

    from . import models, motion
    from .cli.plan import plan_figure
    from .collision import RobotCollision, World, box

    title = "Motion planning around an obstacle"
    urdf = _shipped("fr3")
    if not urdf.exists():
        report.add(title, f"Skipped: {_NOT_SHIPPED.format(urdf)}")
        return
    d = torch.float64
    chain = models.from_urdf(urdf, "fr3_link8", dtype=d).requires_grad_(False)
    srdf = '<robot><disable_collisions link1="fr3_link1_sc" link2="fr3_link3_sc" reason="Default"/></robot>'
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the FR3's meshes are not shipped: Franka's primitives remain
        rc = RobotCollision.from_urdf(urdf, chain, srdf=srdf).requires_grad_(False)
    table = box(center=torch.tensor([0.55, 0.0, 0.05], dtype=d), half_extents=torch.tensor([0.2, 0.5, 0.05],
                                                                                            dtype=d), dtype=d)
    world = World(spheres=torch.tensor([[0.5, 0.0, 0.45, 0.12]], dtype=d), boxes=table, dtype=d)
    q0 = torch.tensor([[0.8, 0.3, 0.0, -1.8, 0.0, 2.1, 0.785]], dtype=d)
    q1 = torch.tensor([[-0.8, 0.3, 0.0, -1.8, 0.0, 2.1, 0.785]], dtype=d)
    acc, jerk = 5.0, 100.0
    with torch.no_grad():
        f = torch.linspace(0, 1, 101, dtype=d)[:, None]
        straight = float(rc.min_distance(q0 + f * (q1 - q0), world).min())
    res, dt = _timed(lambda: motion.plan(chain, q0, q1, collision=rc, world=world, acceleration_limit=acc,
                                         jerk_limit=jerk, resolution=0.01 if quick else 0.005))
    vel = chain.velocity_limits()
    ok = bool(res.success[0])
    with torch.no_grad():
        clear = float(rc.min_distance(res.q[0], world).min())
    rows = [["success", ok or res.reason[0]], ["planning time [s]", f"{dt:.2f}"],
            ["duration [s]", f"{float(res.duration[0]):.3f}"],
            ["waypoints / path", f"{int(res.n_waypoints[0])} / {res.interpolation[0] or '-'}"],
            ["clearance of the straight line [mm]", f"{straight * 1e3:.0f}"],
            ["clearance of the plan (10 ms samples) [mm]", f"{clear * 1e3:.0f}"],
            ["max abs(q̇) / velocity limit", f"{float((res.qd[0].abs() / vel).max()):.3f}"],
            ["max abs(q̈) / acceleration limit", f"{float(res.qdd[0].abs().max()) / acc:.3f}"]]
    plan_figure(res, chain, vel, acc, 0, title="FR3 around a sphere: q, q̇, q̈ (dashed: limits)").savefig(
        report.out / "motion_plan.png", dpi=110)
    body = (
        "`motion.plan` on the FR3 (Franka's capsule model) from one side of a sphere (r = 12 cm) above a "
        "table to the other: the straight joint-space line passes through the sphere; the plan is "
        "RRT-Connect, shortcutting, a continuously checked spline and time-optimal timing under the URDF's "
        f"velocity limits, {acc:g} rad/s² and {jerk:g} rad/s³ (`diffkin plan` writes the same to .npz / "
        ".csv):"
        "\n\n" + _md_table(["", "value"], rows) + "\n\n![planned motion](motion_plan.png)\n")
    report.add(title, body)
    if not ok or clear < 0:
        report.failures.append(f"motion planning: {res.reason[0] or 'a sample in collision'}")


def run_demo(quick: bool = False, out: str | None = None, skip_rl: bool = False) -> int:
    """Run the tour and write ``report.md`` and PNGs to ``out`` (default ``runs/demo-<time>``).

    Runs on torch's current thread count (the report states it); ``diffkin demo`` sets one thread first,
    since small batched kernels gain nothing from intra-op threads and lose a lot when another process
    holds a core."""
    from ._console import console

    try:
        from rich.markdown import Markdown
    except ImportError:  # without the `cli` extra the report prints as plain Markdown
        Markdown = str
    con = console()
    _figure_module()  # the report's figures need matplotlib: say so before any work
    out_dir = Path(out) if out else Path("runs") / time.strftime("demo-%Y%m%d-%H%M%S")
    out_dir.mkdir(parents=True, exist_ok=True)
    report = Report(out_dir)
    steps = [
        ("kernels", lambda: section_kernels(report, quick)),
        ("batch IK", lambda: section_ik(report, 1_000 if quick else 10_000, 200 if quick else 1_000)),
        ("IK layer", lambda: section_ik_layer(report, quick)),
        ("URDF trees", lambda: section_trees(report, quick)),
        ("MuJoCo models", lambda: section_mjcf(report, quick)),
        ("calibration", lambda: section_calibration(report, 60 if quick else 100)),
        ("camera calibration", lambda: section_camera_calibration(report, quick)),
        ("CLIK §3.7.5", lambda: section_clik(report, quick)),
        ("collision-free IK", lambda: section_collision_ik(report, quick)),
        ("teleoperation", lambda: section_teleop(report, quick)),
        ("retargeting", lambda: section_retarget(report, quick)),
        ("motion planning", lambda: section_motion(report, quick)),
    ]
    if not skip_rl:
        steps.append(("RL", lambda: section_rl(report, 15 if quick else 150)))
    t_all = time.perf_counter()
    for name, fn in steps:
        with con.status(f"[bold]{name}[/bold] ..."):
            t0 = time.perf_counter()
            fn()
        con.print(f"[green]✓[/green] {name} ({time.perf_counter() - t0:.1f} s)")
        con.print(Markdown(report.sections[-1]))
    path = report.write()
    con.print(f"\nreport written to [bold]{path}[/bold] ({time.perf_counter() - t_all:.0f} s in all)")
    for f in report.failures:
        con.print(f"[red]problem:[/red] {f}")
    return 1 if report.failures else 0

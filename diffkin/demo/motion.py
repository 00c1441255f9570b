"""``diffkin demo`` sections: CLIK §3.7.5, collision-free IK, teleoperation and motion planning."""

from __future__ import annotations

import math
import statistics
import time

import torch

from ..errors import require
from ._common import _NOT_SHIPPED, Report, _figure, _md_table, _shipped, _timed

__all__ = ["section_clik", "section_collision_ik", "section_teleop", "section_motion"]


def _book_circle(t_end: float, dt: float):
    """§3.7.5 target: p_d(t) on a circle of radius 0.25 m centred at (0.25, 0.5) m, one turn every 2 s
    for 4 s, then at rest; φ_d(t) = sin(πt/24). Returns ``(x_d, ẋ_d)`` ``(S, 6)`` as [p; RPY angles]."""
    from ..trajectories import Trajectory, cartesian_trajectory, circle_path

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
    from .. import models
    from ..ik import clik

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


def section_collision_ik(report: Report, quick: bool) -> None:
    """ik.solve with and without collision=, world= on the FR3 among spheres (a few seconds)."""
    import warnings

    from .. import models
    from ..collision import RobotCollision, World
    from ..ik import solve

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

    from .. import ik
    from ..models import from_mjcf

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

        from ..models.mjcf import compile_mjcf

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


def section_motion(report: Report, quick: bool) -> None:
    """One planned motion (issue 36): motion.plan on the FR3 around a sphere above a table, its timing
    against the limits and a plot of q, q̇, q̈ with them (`diffkin plan` writes the same)."""
    import warnings

    from .. import models, motion
    from ..cli.plan import plan_figure
    from ..collision import RobotCollision, World, box

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

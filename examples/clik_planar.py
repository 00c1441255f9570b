"""Reproduce §3.7.5 (Figs. 3.15–3.20): inverse kinematics algorithms on the three-link planar arm.

Arm of Table 2.1 with a1 = a2 = a3 = 0.5 m, initial posture q = [π, −π/2, −π/2] (p = [0, 0.5] m, φ = 0).
The end effector runs twice round the circle of radius 0.25 m centred at (0.25, 0.5) m in 4 s,
p_d(t) = [0.25(1 − cos πt), 0.25(2 + sin πt)], while φ_d(t) = sin(πt/24); then the target stops and the
runs go on to t = 5 s. Forward Euler with Δt = 1 ms (3.48).

Runs: open-loop Jacobian inverse (3.47) (Fig. 3.15); closed-loop Jacobian inverse (3.70), K = diag(500, 500,
100) (Fig. 3.16); position only (2 task rows, one redundant DOF): pseudo-inverse (3.72) with K = diag(500,
500) (Fig. 3.17) and transpose (3.76) (Fig. 3.18); pseudo-inverse with q̇₀ = k₀ ∂w/∂q (3.55) for
w = ½(s2² + s3²), k₀ = 50 (Fig. 3.19) and for the joint-limit distance (3.57), k₀ = 250, limits
q1 ∈ [−2π, 2π], q2 ∈ [−π/2, π/2], q3 ∈ [−3π/2, −π/2] (Fig. 3.20).

Usage: ``python examples/clik_planar.py [--out runs/examples/clik] [--duration 5]``. Writes fig3_15.png …
fig3_20.png and summary.md into --out and prints the summary table.
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402

from diffkin.chain import DHChain  # noqa: E402
from diffkin.ik.closed_loop import clik, joint_limit_objective  # noqa: E402
from diffkin.trajectories import Trajectory, cartesian_trajectory, circle_path  # noqa: E402

PI = math.pi
DT = 1e-3
T_MOTION = 4.0
LIMITS = torch.tensor([[-2 * PI, 2 * PI], [-PI / 2, PI / 2], [-3 * PI / 2, -PI / 2]], dtype=torch.float64)


def planar_arm() -> DHChain:
    """Table 2.1 with a_i = 0.5 m."""
    z = torch.zeros(3, dtype=torch.float64)
    return DHChain(torch.full((3,), 0.5, dtype=torch.float64), z, z, z, joint_types="RRR", name="planar_3r")


def desired():
    """x_d = [p; φ] (RPY, φ about z) and ẋ_d, sampled every Δt on [0, 4] s: ``(S, 6)`` each.

    The circle comes from the path primitive (4.38) with the linear timing law s(t) = 0.25 π t, and is
    checked against the book's closed form. The velocity of the last sample is zero: the motion stops at
    t = 4 s and the target then holds still (``clik`` holds the last sample).
    """
    t = torch.arange(round(T_MOTION / DT) + 1, dtype=torch.float64) * DT
    speed = 0.25 * PI  # arc length per second: radius 0.25 m, one circle every 2 s
    timing = Trajectory(speed * t, torch.full_like(t, speed), torch.zeros_like(t))
    centre = torch.tensor([0.25, 0.5, 0.0], dtype=torch.float64)
    start = torch.tensor([0.0, 0.5, 0.0], dtype=torch.float64)
    axis = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)  # clockwise seen from +z
    p, v, _ = cartesian_trajectory(lambda s: circle_path(centre, axis, start, s), timing)
    book = torch.stack([0.25 * (1 - torch.cos(PI * t)), 0.25 * (2 + torch.sin(PI * t))], dim=-1)
    assert torch.allclose(p[:, :2], book, atol=1e-12), "circle primitive disagrees with the book's p_d(t)"
    phi, dphi = torch.sin(PI / 24 * t), PI / 24 * torch.cos(PI / 24 * t)
    zero = torch.zeros_like(t)
    x = torch.cat([p, torch.stack([phi, zero, zero], -1)], -1)
    xd = torch.cat([v, torch.stack([dphi, zero, zero], -1)], -1)
    xd[-1] = 0.0
    return x, xd


def manipulability_w(q: torch.Tensor) -> torch.Tensor:
    """The book's simplified manipulability w(ϑ2, ϑ3) = ½(s2² + s3²)."""
    return 0.5 * (torch.sin(q[..., 1]) ** 2 + torch.sin(q[..., 2]) ** 2)


def run_all(duration: float) -> dict:
    chain = planar_arm()
    q0 = torch.tensor([PI, -PI / 2, -PI / 2], dtype=torch.float64)
    x, xd = desired()
    steps = round(duration / DT)
    full = dict(orientation="euler", convention="RPY", rows=(0, 1, 3))
    pos = dict(orientation=None, rows=(0, 1))
    xp, vp = x[:, :3], xd[:, :3]
    runs = {
        "open_loop": (dict(algorithm="inverse", K=0.0, **full), (x, xd)),
        "inverse": (dict(algorithm="inverse", K=[500.0, 500.0, 100.0], **full), (x, xd)),
        "pseudo_inverse": (dict(algorithm="pseudo_inverse", K=500.0, **pos), (xp, vp)),
        "transpose": (dict(algorithm="transpose", K=500.0, **pos), (xp, vp)),
        "nullspace_manipulability": (
            dict(algorithm="pseudo_inverse", K=500.0, nullspace=manipulability_w, k0=50.0, **pos),
            (xp, vp),
        ),
        "nullspace_joint_limits": (
            dict(
                algorithm="pseudo_inverse",
                K=500.0,
                nullspace="joint_limits",
                k0=250.0,
                q_limits=LIMITS,
                **pos,
            ),  # fmt: skip
            (xp, vp),
        ),
    }
    out = {}
    for name, (kw, target) in runs.items():
        t0 = time.perf_counter()
        out[name] = clik(chain, target, q0, DT, steps, **kw)
        print(f"  {name:26s} {steps} steps in {time.perf_counter() - t0:5.1f} s")
    return out


# ------------------------------------------------------------------------------------------ figures
def _plot(ax, t, y, ylabel, title=None, **kw):
    ax.plot(t, y, **kw)
    _style(ax, ylabel, title)


def _style(ax, ylabel, title=None):
    ax.set_xlabel("[s]")
    ax.set_ylabel(ylabel)
    ax.grid(True, alpha=0.3)
    if title:
        ax.set_title(title, fontsize=10)


def _joints(ax, t, q, title, limits=None):
    for i, style in enumerate(["-", "--", "-."]):
        ax.plot(t, q[:, i], style, label=f"joint {i + 1}")
    if limits is not None:
        for i, c in ((1, "C1"), (2, "C2")):
            for v in limits[i]:
                ax.axhline(float(v), color=c, ls=":", lw=1)
    ax.set_xlabel("[s]")
    ax.set_ylabel("[rad]")
    ax.set_title(title, fontsize=10)
    ax.legend(fontsize=8)
    ax.grid(True, alpha=0.3)


def figures(res: dict, out: Path) -> None:
    t = res["inverse"].t.numpy()

    def save(fig, name):
        fig.tight_layout()
        fig.savefig(out / name, dpi=110)
        plt.close(fig)

    r = res["open_loop"]
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.6))
    _plot(ax[0], t, r.position_error, "[m]", "pos error norm (open loop)")
    _plot(ax[1], t, r.orientation_error, "[rad]", "orientation error norm (open loop)")
    save(fig, "fig3_15.png")

    r = res["inverse"]
    fig, ax = plt.subplots(2, 2, figsize=(10, 7))
    _joints(ax[0, 0], t, r.q, "joint pos (Jacobian inverse, K=diag(500,500,100))")
    _joints(ax[0, 1], t, r.qdot, "joint vel")
    ax[0, 1].set_ylabel("[rad/s]")
    _plot(ax[1, 0], t, r.position_error, "[m]", "pos error norm")
    _plot(ax[1, 1], t, r.orientation_error, "[rad]", "orientation error norm")
    save(fig, "fig3_16.png")

    for key, name, title in (
        ("pseudo_inverse", "fig3_17.png", "Jacobian pseudo-inverse"),
        ("transpose", "fig3_18.png", "Jacobian transpose"),
    ):
        r = res[key]
        fig, ax = plt.subplots(1, 2, figsize=(10, 3.6))
        _plot(ax[0], t, r.position_error, "[m]", f"pos error norm ({title}, K=diag(500,500))")
        _plot(ax[1], t, r.q.sum(-1), "[rad]", "end-effector orientation φ = q1+q2+q3 (free)")
        save(fig, name)

    free, con = res["pseudo_inverse"], res["nullspace_manipulability"]
    fig, ax = plt.subplots(2, 2, figsize=(10, 7))
    _joints(ax[0, 0], t, free.q, "joint pos, unconstrained (k0 = 0)")
    _joints(ax[0, 1], t, con.q, "joint pos, manipulability constraint (k0 = 50)")
    _plot(ax[1, 0], t, con.position_error, "[m]", "pos error norm (constrained)")
    ax[1, 1].plot(t, manipulability_w(con.q), "-", label="constrained")
    ax[1, 1].plot(t, manipulability_w(free.q), "--", label="unconstrained")
    _style(ax[1, 1], "", "manipulability w = ½(s2² + s3²)")
    ax[1, 1].legend(fontsize=8)
    save(fig, "fig3_19.png")

    r = res["nullspace_joint_limits"]
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.8))
    _joints(ax[0], t, r.q, "joint pos, joint-limit constraint (k0 = 250)", limits=LIMITS)
    _plot(ax[1], t, r.position_error, "[m]", "pos error norm")
    save(fig, "fig3_20.png")


# ------------------------------------------------------------------------------------------ summary
def _violation(q: torch.Tensor) -> float:
    lo, hi = LIMITS[:, 0], LIMITS[:, 1]
    return float(torch.maximum(lo - q, q - hi).clamp_min(0).max())


def summary(res: dict) -> str:
    k_full, k_pos = "diag(500, 500, 100)", "diag(500, 500)"
    rows = [
        ("open loop (3.47)", "open_loop", "0"),
        ("Jacobian inverse (3.70)", "inverse", k_full),
        ("pseudo-inverse (3.72), q̇₀ = 0", "pseudo_inverse", k_pos),
        ("transpose (3.76)", "transpose", k_pos),
        ("pseudo-inverse + manipulability, k0 = 50", "nullspace_manipulability", k_pos),
        ("pseudo-inverse + joint limits, k0 = 250", "nullspace_joint_limits", k_pos),
    ]
    lines = [
        "| algorithm | K | final pos err [m] | max pos err [m] | final orient err [rad] "
        "| max orient err [rad] |",
        "|---|---|---|---|---|---|",
    ]
    for label, key, K in rows:
        r = res[key]
        has_o = key in ("open_loop", "inverse")
        o_fin = f"{float(r.orientation_error[-1]):.2e}" if has_o else "— (free)"
        o_max = f"{float(r.orientation_error.max()):.2e}" if has_o else "— (free)"
        lines.append(
            f"| {label} | {K} | {float(r.position_error[-1]):.2e} | {float(r.position_error.max()):.2e} "
            f"| {o_fin} | {o_max} |"
        )
    free, man, lim = res["pseudo_inverse"], res["nullspace_manipulability"], res["nullspace_joint_limits"]
    i_circle = min(round(2.0 / DT), free.q.shape[0] - 1)  # one circle (or the end of a short run)
    lines += [
        "",
        "| null-space objective | unconstrained (k0 = 0) | constrained |",
        "|---|---|---|",
        f"| w = ½(s2²+s3²): mean over t | {float(manipulability_w(free.q).mean()):.3f} "
        f"| {float(manipulability_w(man.q).mean()):.3f} |",
        f"| w = ½(s2²+s3²): min over t | {float(manipulability_w(free.q).min()):.3f} "
        f"| {float(manipulability_w(man.q).min()):.3f} |",
        f"| max \\|q(2 s) − q(0)\\| after one circle [rad] "
        f"| {float((free.q[i_circle] - free.q[0]).abs().max()):.3f} "
        f"| {float((man.q[i_circle] - man.q[0]).abs().max()):.3f} |",
        f"| joint-limit distance (3.57): min over t | "
        f"{float(joint_limit_objective(free.q, LIMITS[:, 0], LIMITS[:, 1]).min()):.4f} "
        f"| {float(joint_limit_objective(lim.q, LIMITS[:, 0], LIMITS[:, 1]).min()):.4f} |",
        f"| max joint-limit violation [rad] | {_violation(free.q):.3f} | {_violation(lim.q):.3f} |",
    ]
    return "\n".join(lines)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("runs/examples/clik"))
    ap.add_argument("--duration", type=float, default=5.0, help="simulated time [s] (4 s motion + rest)")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    print(f"§3.7.5 on the three-link planar arm, Δt = {DT * 1e3:g} ms, {args.duration:g} s:")
    res = run_all(args.duration)
    figures(res, args.out)
    table = summary(res)
    (args.out / "summary.md").write_text(
        "# §3.7.5: comparison among inverse kinematics algorithms (three-link planar arm)\n\n" + table + "\n"
    )
    print(table)
    print(f"figures and summary.md in {args.out}/")


if __name__ == "__main__":
    main()

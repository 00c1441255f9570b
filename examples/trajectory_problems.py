"""Textbook ch. 4 problems 4.1, 4.3, 4.5, 4.6, 4.7 and 4.8 solved with diffkin.trajectories.

Prints each answer and writes one PNG per problem.

    python examples/trajectory_problems.py --out runs/examples/
"""

from __future__ import annotations

import argparse
import functools
import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from diffkin import trajectories as tr  # noqa: E402

F64 = torch.float64
PI = math.pi
# Problems 4.3, 4.5, 4.6 share the data q(0) = 0, q(2) = 2, q(4) = 3.
POINTS = torch.tensor([[0.0], [2.0], [3.0]], dtype=F64)
TIMES = torch.tensor([0.0, 2.0, 4.0], dtype=F64)


def tt(x):
    return torch.as_tensor(x, dtype=F64)


def poly_str(c, var="t") -> str:
    terms = [
        f"{a:+.6g}" + ("" if k == 0 else f" {var}" if k == 1 else f" {var}^{k}") for k, a in enumerate(c)
    ]
    return " ".join(t for t, a in zip(terms, c) if abs(a) > 1e-12) or "0"


def _shift(t0: float) -> str:
    return "t" if t0 == 0 else f"(t - {t0:g})" if t0 > 0 else f"(t + {-t0:g})"


def _vec(x) -> list[float]:
    return (np.round(x.numpy(), 6) + 0.0).tolist()


def plot(path: Path, title: str, t, traj, labels=("q",), marks=None, units=("", "/s", "/s^2")) -> None:
    fig, axes = plt.subplots(3, 1, figsize=(5.5, 7), sharex=True)
    for ax, y, name, u in zip(axes, traj, ["position", "velocity", "acceleration"], units):
        y = y.detach().numpy().reshape(len(t), -1)
        for j in range(y.shape[1]):
            ax.plot(t.numpy(), y[:, j], label=labels[j] if j < len(labels) else None)
        ax.set_ylabel(f"{name} {u}".strip())
        ax.grid(True, alpha=0.3)
    if marks is not None:
        axes[0].plot(*marks, "ko", ms=4)
    if len(labels) > 1:
        axes[0].legend(fontsize=8)
    axes[0].set_title(title)
    axes[-1].set_xlabel("t [s]")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    print(f"  wrote {path}")


def problem_4_1(out: Path) -> None:
    print("Problem 4.1: q(0)=1 -> q(2)=4, null initial/final velocity and acceleration -> quintic (4.2)")
    t = torch.linspace(0, 2, 401, dtype=F64)
    traj = tr.quintic(tt([1.0]), tt([4.0]), 2.0, t)
    # Coefficients of (4.2) read back from the samples (a degree-5 fit of a quintic is exact).
    c = np.polynomial.polynomial.polyfit(t.numpy(), traj.position[:, 0].numpy(), 5)
    print(f"  q(t) = {poly_str(c)}   (exact: 1 + 3.75 t^3 - 2.8125 t^4 + 0.5625 t^5)")
    print(f"  max velocity {traj.velocity.max():.6g} at t = 1, max |acc| {traj.acceleration.abs().max():.6g}")
    plot(out / "problem4_1_quintic.png", "Problem 4.1: quintic 1 -> 4 in 2 s", t, traj)


def problem_4_3(out: Path) -> None:
    print(
        "Problem 4.3: two quintics through q(0)=0, q(2)=2, q(4)=3 with continuous velocity and acceleration"
    )
    print(
        "  assumptions: at rest at both ends (q_dot = q_ddot = 0); the 2 remaining degrees of freedom"
        " are fixed"
    )
    print("  by also making jerk and snap continuous at t = 2 (12 conditions, 12 coefficients)")
    rows, rhs = [], []

    def row(seg, tau, der):
        r = np.zeros(12)
        for j in range(der, 6):
            r[6 * seg + j] = math.factorial(j) / math.factorial(j - der) * tau ** (j - der)
        return r

    for der, val in enumerate([0.0, 0.0, 0.0]):  # q, q_dot, q_ddot at t = 0
        rows.append(row(0, 0.0, der)), rhs.append(val)
    for der, val in enumerate([3.0, 0.0, 0.0]):  # at t = 4 (local time 2 of segment 2)
        rows.append(row(1, 2.0, der)), rhs.append(val)
    rows.append(row(0, 2.0, 0)), rhs.append(2.0)
    rows.append(row(1, 0.0, 0)), rhs.append(2.0)
    for der in range(1, 5):  # continuity of derivatives 1..4 at t = 2
        rows.append(row(0, 2.0, der) - row(1, 0.0, der)), rhs.append(0.0)
    c = np.linalg.solve(np.array(rows), np.array(rhs)).reshape(2, 6)
    v_m, a_m = c[1, 1], 2 * c[1, 2]
    print(f"  Pi_1(t)     = {poly_str(c[0])}, 0 <= t <= 2")
    print(f"  Pi_2(t - 2) = {poly_str(c[1], '(t-2)')}, 2 <= t <= 4")
    print(f"  via point t = 2: velocity {v_m:.6g}, acceleration {a_m:.6g}")
    t = torch.linspace(0, 4, 801, dtype=F64)
    first = tr.quintic(tt([0.0]), tt([2.0]), 2.0, t, v_f=v_m, a_f=a_m)
    second = tr.quintic(tt([2.0]), tt([3.0]), 2.0, t - 2, v_i=v_m, a_i=a_m)
    on_first = (t <= 2)[:, None]
    traj = tr.Trajectory(*(torch.where(on_first, a, b) for a, b in zip(first, second)))
    ref = np.where(t.numpy() <= 2, np.polyval(c[0][::-1], t.numpy()), np.polyval(c[1][::-1], t.numpy() - 2))
    print(
        "  library quintics vs the 12x12 solve: max |dq| = "
        f"{np.abs(traj.position[:, 0].numpy() - ref).max():.2e}"
    )
    plot(
        out / "problem4_3_two_quintics.png", "Problem 4.3: two quintics", t, traj, marks=(TIMES, POINTS[:, 0])
    )


def problem_4_5(out: Path) -> None:
    print("Problem 4.5: cubic spline through q(0)=0, q(2)=2, q(4)=3, null end velocities and accelerations")
    print("  (book's construction with two virtual points (4.13)-(4.28), here at t = 1 and t = 3)")
    knots = tt([0.0, 1.0, 2.0, 3.0, 4.0])
    at = tr.cubic_spline(POINTS, TIMES, knots, end="natural_virtual")
    q, qd, qdd = (x[:, 0].numpy() for x in at)
    print(f"  virtual points: q(1) = {q[1]:.6g}, q(3) = {q[3]:.6g}")
    print(f"  knot accelerations at t = 0..4: {np.round(qdd, 6).tolist()}")
    for k in range(4):
        c = [q[k], qd[k], qdd[k] / 2, (qdd[k + 1] - qdd[k]) / 6]
        print(f"  Pi_{k + 1}: {poly_str(c, 'tau')}, tau = t - {k}, {k} <= t <= {k + 1}")
    t = torch.linspace(0, 4, 801, dtype=F64)
    traj = tr.cubic_spline(POINTS, TIMES, t, end="natural_virtual")
    clamped = tr.cubic_spline(POINTS, TIMES, t)  # velocities only: the end accelerations stay free
    print(
        f"  (clamped spline without virtual points: end accelerations {clamped.acceleration[0, 0]:.6g}, "
        f"{clamped.acceleration[-1, 0]:.6g})"
    )
    both = tr.Trajectory(*(torch.cat([a, b], -1) for a, b in zip(traj, clamped)))
    plot(
        out / "problem4_5_spline.png",
        "Problem 4.5: cubic spline",
        t,
        both,
        labels=("virtual points (null end acc.)", "clamped (end acc. free)"),
        marks=(TIMES, POINTS[:, 0]),
    )


def problem_4_6(out: Path) -> None:
    blend = 0.5
    print(f"Problem 4.6: linear segments with parabolic blends through the same points, dt' = {blend} s")
    v = (torch.diff(POINTS[:, 0]) / torch.diff(TIMES)).tolist()  # (4.29)
    vs = [0.0, *v, 0.0]
    acc = [(vs[k + 1] - vs[k]) / blend for k in range(3)]  # (4.30)
    print(f"  segment velocities (4.29): {v}; blend accelerations (4.30): {acc}")
    t = torch.linspace(-0.5, 4.5, 1001, dtype=F64)
    traj = tr.linear_parabolic_blends(POINTS, TIMES, t, blend_time=blend)
    q_at = tr.linear_parabolic_blends(POINTS, TIMES, TIMES, blend_time=blend).position[:, 0].tolist()
    print(
        f"  motion from t = {-blend / 2} to {4 + blend / 2}; "
        f"passes q = {np.round(q_at, 6).tolist()} at t = 0, 2, 4"
    )
    for k, tk in enumerate(TIMES.tolist()):
        lo, hi = tk - blend / 2, tk + blend / 2
        print(
            f"  blend {k + 1}: {lo:g} <= t <= {hi:g}: q = {POINTS[k, 0].item() + vs[k] * (lo - tk):+.6g} "
            f"{vs[k]:+.6g} {_shift(lo)} {acc[k] / 2:+.6g} {_shift(lo)}^2"
        )
        if k < 2:
            print(
                f"  linear:  {hi:g} <= t <= {TIMES[k + 1] - blend / 2:g}: "
                f"q = {POINTS[k, 0].item():g} {vs[k + 1]:+g} {_shift(tk)}"
            )
    plot(
        out / "problem4_6_parabolic_blends.png",
        "Problem 4.6: parabolic blends",
        t,
        traj,
        marks=(TIMES, POINTS[:, 0]),
    )


def _print_trapezoid(L: float, t_f: float) -> None:
    law = tr.timing_law(L, t_f, tt([0.0, t_f / 2]), "trapezoidal")
    t_c, sd_c, sdd_c = t_f / 3, law.velocity[1].item(), law.acceleration[0].item()
    print(
        f"  s(t): path length {L:.6g}, t_c = {t_c:.6g} s, cruise s_dot = {sd_c:.6g}, "
        f"blend s_ddot = {sdd_c:.6g}"
    )
    print(
        f"    s = {sdd_c / 2:.6g} t^2 (t <= {t_c:.4g}); s = {sd_c:.6g} (t - {t_c / 2:.4g}) ({t_c:.4g} < t <= "
        f"{t_f - t_c:.4g}); s = {L:.6g} - {sdd_c / 2:.6g} ({t_f:g} - t)^2 (after)"
    )


def problem_4_7(out: Path) -> None:
    print("Problem 4.7: rectilinear path p(0) = [0, 0.5, 0] -> p(2) = [1, -0.5, 0], trapezoidal velocity")
    p_i, p_f = tt([0.0, 0.5, 0.0]), tt([1.0, -0.5, 0.0])
    L = torch.linalg.norm(p_f - p_i)
    _print_trapezoid(L.item(), 2.0)
    print(
        f"  p(t) = p_i + s(t)/{L.item():.6g} (p_f - p_i) = [0, 0.5, 0] + s(t) [0.707107, -0.707107, 0] (4.34)"
    )
    t = torch.linspace(0, 2, 401, dtype=F64)
    traj = tr.cartesian_trajectory(
        functools.partial(tr.segment_path, p_i, p_f), tr.timing_law(L, 2.0, t, "trapezoidal")
    )
    print(f"  p(1) = {_vec(traj.position[200])}, max speed {traj.velocity.norm(dim=-1).max():.6g}")
    plot(
        out / "problem4_7_segment.png",
        "Problem 4.7: segment, trapezoidal s(t)",
        t,
        traj,
        labels=("x", "y", "z"),
        units=("[m]", "[m/s]", "[m/s^2]"),
    )


def problem_4_8(out: Path) -> None:
    print(
        "Problem 4.8: circle in x = 0, centre [0, 0, 1], rho = 0.5, p(0) = [0, 0.5, 1] -> p(2) = [0, -0.5, 1]"
    )
    print(
        "  'clockwise for an observer aligned with x' read as: looking along +x, i.e. positive rotation"
        " about +x"
    )
    c, r, p_i = tt([0.0, 0.0, 1.0]), tt([1.0, 0.0, 0.0]), tt([0.0, 0.5, 1.0])
    _, rho, R = tr.circle_frame(c, r, p_i)
    L = PI * rho.item()  # half circle
    _print_trapezoid(L, 2.0)
    print(f"  R = [x' y' z'] = {R.numpy().round(6).tolist()}")
    print(
        "  p(t) = c + R [rho cos(s/rho), rho sin(s/rho), 0] = [0, 0.5 cos(2 s), 1 + 0.5 sin(2 s)]"
        " (4.38)-(4.39)"
    )
    t = torch.linspace(0, 2, 401, dtype=F64)
    path = functools.partial(tr.circle_path, c, r, p_i)
    traj = tr.cartesian_trajectory(path, tr.timing_law(L, 2.0, t, "trapezoidal"))
    print(f"  p(1) = {_vec(traj.position[200])}, p(2) = {_vec(traj.position[-1])}")
    plot(
        out / "problem4_8_circle.png",
        "Problem 4.8: circle, trapezoidal s(t)",
        t,
        traj,
        labels=("x", "y", "z"),
        units=("[m]", "[m/s]", "[m/s^2]"),
    )
    fig, ax = plt.subplots(figsize=(4, 4))
    ax.plot(traj.position[:, 1].numpy(), traj.position[:, 2].numpy())
    ax.plot([0.5, -0.5], [1.0, 1.0], "ko")
    ax.set_xlabel("y [m]"), ax.set_ylabel("z [m]"), ax.set_aspect("equal"), ax.grid(True, alpha=0.3)
    ax.set_title("Problem 4.8: path in the plane x = 0")
    fig.tight_layout()
    fig.savefig(out / "problem4_8_circle_path.png", dpi=110)
    plt.close(fig)
    print(f"  wrote {out / 'problem4_8_circle_path.png'}")


def main(out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    for solve in (problem_4_1, problem_4_3, problem_4_5, problem_4_6, problem_4_7, problem_4_8):
        solve(out)
        print()


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("runs/examples"))
    main(parser.parse_args().out)

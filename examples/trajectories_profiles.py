"""Joint-space timing laws of textbook ch. 4 in the style of Figs. 4.1-4.10: position, velocity and
acceleration profiles, with the book's data. One PNG per figure.

    python examples/trajectories_profiles.py --out runs/examples/
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402

from diffkin import trajectories as tr  # noqa: E402

PI = math.pi
F64 = torch.float64
# Path points of Figs. 4.5-4.9: q = 0, 2pi, pi/2, pi at t = 0, 2, 3, 5
POINTS = torch.tensor([[0.0], [2 * PI], [PI / 2], [PI]], dtype=F64)
TIMES = torch.tensor([0.0, 2.0, 3.0, 5.0], dtype=F64)


def plot_profiles(path: Path, title: str, curves, marks=None) -> None:
    """curves: list of (t, Trajectory, style, label); marks: (times, positions) drawn as dots."""
    fig, axes = plt.subplots(3, 1, figsize=(5.5, 7), sharex=True)
    for t, traj, style, label in curves:
        for ax, y in zip(axes, traj):
            ax.plot(t.numpy(), y[..., 0].detach().numpy(), style, label=label)
    if marks is not None:
        axes[0].plot(marks[0].numpy(), marks[1].numpy(), "ko", ms=4)
    for ax, name in zip(axes, ["pos [rad]", "vel [rad/s]", "acc [rad/s^2]"]):
        ax.set_ylabel(name)
        ax.grid(True, alpha=0.3)
    axes[-1].set_xlabel("[s]")
    axes[0].set_title(title)
    if any(c[3] for c in curves):
        axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    print(f"wrote {path}")


def main(out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    q0, qpi = torch.tensor([0.0], dtype=F64), torch.tensor([PI], dtype=F64)
    t1 = torch.linspace(0, 1, 401, dtype=F64)
    t5 = torch.linspace(0, 5, 1001, dtype=F64)

    cub = tr.cubic(q0, qpi, 1.0, t1)
    plot_profiles(out / "fig4_1_cubic.png", "Fig. 4.1: cubic, q_i=0, q_f=pi, t_f=1", [(t1, cub, "-", "")])

    trap = tr.trapezoidal(q0, qpi, 1.0, t1, qdd_c=6 * PI)
    plot_profiles(
        out / "fig4_3_trapezoidal.png",
        "Fig. 4.3: trapezoidal velocity, |qdd_c| = 6 pi",
        [
            (t1, trap, "-", "qdd_c = 6 pi"),
            (t1, tr.trapezoidal(q0, qpi, 1.0, t1), "--", "default t_c = t_f/3"),
        ],
    )

    vel = torch.tensor([[0.0], [PI], [-PI], [0.0]], dtype=F64)
    imposed = tr.cubic_through_points(POINTS, TIMES, t5, velocities=vel)
    plot_profiles(
        out / "fig4_5_imposed_velocities.png",
        "Fig. 4.5: cubics with imposed velocities",
        [(t5, imposed, "-", "")],
        (TIMES, POINTS[:, 0]),
    )

    computed = tr.cubic_through_points(POINTS, TIMES, t5)
    plot_profiles(
        out / "fig4_6_computed_velocities.png",
        "Fig. 4.6: cubics with velocities by rule (4.12)",
        [(t5, computed, "-", "")],
        (TIMES, POINTS[:, 0]),
    )

    # Fig. 4.7 uses q1=0, q3=2pi, q4=pi/2, q6=pi at t = 0, 2, 3, 5 and virtual points in between
    spl = [
        (
            t5,
            tr.cubic_spline(
                POINTS, TIMES, t5, end="natural_virtual", virtual_times=torch.tensor(vt, dtype=F64)
            ),
            s,
            lab,
        )
        for vt, s, lab in [
            ([0.5, 4.5], "-", "virtual t = 0.5, 4.5"),
            ([1.5, 3.5], "--", "virtual t = 1.5, 3.5"),
        ]
    ]
    plot_profiles(
        out / "fig4_7_spline_virtual_points.png",
        "Fig. 4.7: splines, two virtual-point pairs",
        spl,
        (TIMES, POINTS[:, 0]),
    )

    tb = torch.linspace(-0.4, 5.4, 1161, dtype=F64)
    blends = [
        (tb, tr.linear_parabolic_blends(POINTS, TIMES, tb, blend_time=d), s, f"dt' = {d}")
        for d, s in [(0.2, "-"), (0.6, "--")]
    ]
    plot_profiles(
        out / "fig4_9_parabolic_blends.png",
        "Fig. 4.9: linear segments with parabolic blends",
        blends,
        (TIMES, POINTS[:, 0]),
    )

    t2 = torch.linspace(0, 2, 801, dtype=F64)
    pts = torch.tensor([[0.0], [PI], [1.5 * PI]], dtype=F64)
    tms = torch.tensor([0.0, 1.0, 2.0], dtype=F64)
    acc = torch.tensor([6 * PI, 3 * PI], dtype=F64)
    ant = [
        (
            t2,
            tr.anticipated_segments(pts, tms, t2, advance=torch.tensor([0.0, a], dtype=F64), qdd_c=acc),
            s,
            lab,
        )
        for a, s, lab in [(0.18, "-", "anticipation 0.18 s"), (0.0, ":", "no anticipation")]
    ]
    plot_profiles(
        out / "fig4_10_anticipation.png", "Fig. 4.10: second segment anticipated", ant, (tms, pts[:, 0])
    )


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("runs/examples"))
    main(parser.parse_args().out)

"""Manipulability ellipses of the two-link planar arm (textbook §3.9, Figs. 3.23–3.25, Example 3.6).

Postures with the tip on the horizontal axis and a1 = a2 = 1 m, as in the book: velocity ellipses
(Fig. 3.23), force ellipses (Fig. 3.25), the extreme singular values of J against the tip distance r
(Fig. 3.24) and the manipulability w = a1 a2 |s2| (Example 3.6). Everything is computed in one batch by
diffkin's Jacobian, ellipsoid and manipulability functions.

    python examples/manipulability_ellipses.py [--out runs/examples/]
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402
from matplotlib.patches import Ellipse  # noqa: E402

from diffkin import DHChain  # noqa: E402
from diffkin.jacobian import geometric_jacobian  # noqa: E402
from diffkin.manipulability import force_ellipsoid, manipulability, velocity_ellipsoid  # noqa: E402

A1 = A2 = 1.0


def two_link() -> DHChain:
    z = torch.zeros(2, dtype=torch.float64)
    return DHChain(torch.tensor([A1, A2], dtype=torch.float64), z, z, z, name="two_link_planar")


def tip_on_x_axis(r: torch.Tensor) -> torch.Tensor:
    """Closed-form inverse kinematics (elbow up) placing the tip at (r, 0): (...) -> (..., 2)."""
    c2 = ((r**2 - A1**2 - A2**2) / (2 * A1 * A2)).clamp(-1.0, 1.0)
    th2 = -torch.acos(c2)
    th1 = -torch.atan2(A2 * torch.sin(th2), A1 + A2 * torch.cos(th2))
    return torch.stack((th1, th2), dim=-1)


def draw_postures(ax, chain, q, ellipsoid, scale: float, title: str, color: str) -> None:
    """Arm postures and, at each tip, the ellipse with semi-axes ``scale * lengths``."""
    frames = chain.forward_kinematics(q, all_frames=True).detach()  # (k, 3, 4, 4)
    for k in range(q.shape[0]):
        pts = frames[k, :, :2, 3].numpy()
        ax.plot(pts[:, 0], pts[:, 1], "-o", color="0.45", lw=1.5, ms=3)
        axes, lengths = ellipsoid.axes[k].numpy(), ellipsoid.lengths[k].numpy()
        angle = math.degrees(math.atan2(axes[1, 0], axes[0, 0]))
        ax.add_patch(Ellipse(pts[-1], 2 * scale * lengths[0], 2 * scale * lengths[1], angle=angle,
                             fill=False, color=color, lw=1.8))  # fmt: skip
    ax.set_title(title)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.grid(alpha=0.3)


def make_figure(out: Path) -> Path:
    chain = two_link()
    with torch.no_grad():
        r_post = torch.tensor([0.4, 0.8, 1.2, 1.6, 1.9], dtype=torch.float64)
        q_post = tip_on_x_axis(r_post)
        J_post = geometric_jacobian(chain, q_post)[..., :2, :]  # planar rows (3.40)
        vel, force = velocity_ellipsoid(J_post), force_ellipsoid(J_post)

        r = torch.linspace(0.0, 2.0, 401, dtype=torch.float64)
        J = geometric_jacobian(chain, tip_on_x_axis(r))[..., :2, :]
        sigma = velocity_ellipsoid(J).lengths
        w = manipulability(J)

    fig, axs = plt.subplots(2, 2, figsize=(12, 9))
    title_v = "Velocity manipulability ellipses (Fig. 3.23), ×0.25"
    title_f = "Force manipulability ellipses (Fig. 3.25), ×0.1"
    draw_postures(axs[0, 0], chain, q_post, vel, 0.25, title_v, "C0")
    draw_postures(axs[0, 1], chain, q_post, force, 0.1, title_f, "C3")
    for ax in axs[0]:
        ax.set_xlim(-0.4, 2.4)
        ax.set_ylim(-0.3, 1.3)
    ax = axs[1, 0]
    ax.plot(r, sigma[:, 0], label=r"$\sigma_{max}$")
    ax.plot(r, sigma[:, 1], label=r"$\sigma_{min}$")
    ax.set_title("Singular values of J vs tip position (Fig. 3.24)")
    ax.set_xlabel("r = x [m]")
    ax.set_ylabel("[m]")
    ax.legend()
    ax.grid(alpha=0.3)
    ax = axs[1, 1]
    ax.plot(r, w, color="C2", label=r"$w = \sqrt{\det(JJ^T)}$ (diffkin)")
    book = A1 * A2 * torch.sin(tip_on_x_axis(r[::20])[:, 1]).abs()  # w = a1 a2 |s2|
    ax.plot(r[::20], book, "k.", label=r"$a_1 a_2 |s_2|$ (3.41)")
    ax.set_title("Manipulability vs tip position (Example 3.6)")
    ax.set_xlabel("r = x [m]")
    ax.set_ylabel("w [m²]")
    ax.legend()
    ax.grid(alpha=0.3)
    fig.suptitle("Two-link planar arm, a1 = a2 = 1 m: tip on the x axis")
    fig.tight_layout()
    out.mkdir(parents=True, exist_ok=True)
    path = out / "manipulability_ellipses.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("runs/examples"), help="output folder for the PNG")
    args = parser.parse_args(argv)
    print(make_figure(args.out))


if __name__ == "__main__":
    main()

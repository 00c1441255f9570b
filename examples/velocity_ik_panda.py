"""Track a Cartesian path with a Panda at its joint limits: CLIK with hard limits (issue 29).

The Panda starts in a ready pose with its last joint (the flange roll, joint 7, range ±2.8973 rad) at
2.5 rad; its flange moves 0.15 m along y and back while turning about its own z axis by up to 0.8 rad
(θ(t) = 0.8 sin(πt/4), t ∈ [0, 4] s), at Δt = 10 ms. Joint 7 alone would have to reach 3.3 rad: it runs
into its limit at θ ≈ 0.4 rad, and the other six joints must produce the rest of the roll. Three CLIK runs
of the damped-least-squares law (3.59), k = 0.01, K = 20, position and orientation (axis-angle error):

* ``dls``: no limits: joint 7 runs through its limit (an infeasible joint motion);
* ``dls + clamp``: the same step, q clamped onto the limits after each step: the motion the clamp removes
  is lost, the orientation error grows to the part of θ joint 7 could not follow;
* ``velocity_step``: ``clik(..., limits=True)``: each q̇ solves the DLS problem exactly under the position
  limits over Δt and |q̇| ≤ 2 rad/s, so the other joints take over joint 7's share while it rests at its
  limit.

Usage: ``python examples/velocity_ik_panda.py [--out docs/img/velocity_ik_panda.png]``; prints the largest
position / orientation errors and the limit violations of each run.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402

from diffkin import ik, models  # noqa: E402

DT, DURATION, SHIFT, ROLL = 0.01, 4.0, 0.15, 0.8
Q0 = [0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 2.5]


def path(chain, q0):
    """Poses (S, 4, 4) and twists [v; ω] (S, 6) (base frame) of the shift along y with the flange roll."""
    T0 = chain.forward_kinematics(q0)
    t = torch.arange(round(DURATION / DT) + 1, dtype=torch.float64) * DT
    w = math.pi / DURATION
    s, ds = torch.sin(w * t), w * torch.cos(w * t)
    theta = ROLL * s
    c, n = torch.cos(theta), torch.sin(theta)
    Rz = torch.zeros(len(t), 3, 3, dtype=torch.float64)
    Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2] = c, -n, n, c, 1.0
    T = T0.expand(len(t), 4, 4).clone()
    T[:, :3, :3] = T0[:3, :3] @ Rz  # a turn about the flange's own z axis
    T[:, 1, 3] += SHIFT * s
    twist = torch.zeros(len(t), 6, dtype=torch.float64)
    twist[:, 1] = SHIFT * ds
    twist[:, 3:] = (ROLL * ds)[:, None] * T0[:3, 2]  # ω = θ̇ z_flange (z is fixed by a turn about it)
    return t, T, twist


def runs(chain, q0, target):
    common = dict(algorithm="dls", orientation="axis_angle", damping=1e-4, K=20.0)
    return {"dls": ik.clik(chain, target, q0, DT, **common),
            "dls + clamp": ik.clik(chain, target, q0, DT, clamp=True, **common),
            "velocity_step": ik.clik(chain, target, q0, DT, limits=True, qdot_max=2.0, **common)}


def violation(chain, q):
    lo, hi = chain.q_limits[:, 0], chain.q_limits[:, 1]
    return float(torch.maximum(lo - q, q - hi).clamp(min=0).max())


def plot(t, chain, results, out: Path):
    fig, ax = plt.subplots(1, 3, figsize=(13, 3.6))
    hi = float(chain.q_limits[6, 1])
    for name, r in results.items():
        ax[0].plot(t, 1e3 * r.position_error, label=name)
        ax[1].plot(t, torch.rad2deg(r.orientation_error), label=name)
        ax[2].plot(t, r.q[:, 6], label=name)
    ax[2].axhline(hi, color="k", ls="--", lw=1, label="joint 7 upper limit")
    ax[0].set(xlabel="t [s]", ylabel="position error [mm]", yscale="log")
    ax[1].set(xlabel="t [s]", ylabel="orientation error [deg]", yscale="log")
    ax[2].set(xlabel="t [s]", ylabel="q7 [rad]")
    for a in ax:
        a.grid(alpha=0.3)
    ax[2].legend(fontsize=8)
    fig.suptitle("Panda: shift and flange roll beyond joint 7's limit, Δt = 10 ms; CLIK (DLS) without "
                 "limits, with a clamp, with velocity_step")
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default="docs/img/velocity_ik_panda.png")
    args = p.parse_args(argv)
    chain = models.load("panda", dtype=torch.float64).requires_grad_(False)
    q0 = torch.tensor(Q0, dtype=torch.float64)
    t, T, twist = path(chain, q0)
    results = runs(chain, q0, (T, twist))
    print(f"{'run':>14}  {'max pos err [mm]':>16}  {'max ori err [deg]':>17}  {'limit violation [rad]':>21}")
    for name, r in results.items():
        print(f"{name:>14}  {1e3 * float(r.position_error.max()):16.3f}  "
              f"{math.degrees(float(r.orientation_error.max())):17.3f}  {violation(chain, r.q):21.4f}")
    plot(t, chain, results, Path(args.out))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Teleoperation at 500 Hz: differential IK following a moving target, with limits (issue 35).

Each tick (Δt = 2 ms) builds the tasks for the newest target and asks ``ik.solve_velocity`` for q̇ (mink's
``solve_ik`` semantics: weighted frame and posture tasks, joint position and velocity limits as hard
constraints), then integrates q ← q ⊕ q̇Δt. On the CPU without autograd the call is one C step.

* ``panda``: the Menagerie Panda's hand follows a 5 cm circle (0.5 Hz) while turning about its own z axis;
  posture towards the start, ConfigurationLimit (gain 0.95) and |q̇| ≤ 2 rad/s on every joint.
* ``g1``: the Unitree G1 from its MJCF (floating base): both feet held where they stand (frame tasks), both
  hands on 8 cm circles, a posture task on the joints, ConfigurationLimit and |q̇| ≤ 4 rad/s on the hinges.
  (No centre-of-mass task here: it needs the chain's mass model.)

Printed per robot: the tick time percentiles (the whole tick: tasks, solve, integration; 2 000 µs is the
500 Hz budget; and the median of the solve alone), the worst joint-limit margin over the run (min over
steps and joints of the distance to the nearer position limit; negative would be a violation), the largest
|q̇| / q̇_max, and the tracking error.

Usage: ``python examples/teleop.py [--robot panda|g1|both] [--seconds 4] [--realtime]`` (``--realtime``
sleeps out each 2 ms tick, as a control loop would).
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np
import torch

from diffkin import ik
from diffkin.models import from_mjcf

ROOT = Path(__file__).resolve().parents[1]
PANDA = ROOT / "tests" / "data" / "mjcf" / "franka_emika_panda" / "panda.xml"
G1 = ROOT / "tests" / "data" / "mjcf" / "unitree_g1" / "g1.xml"
DT = 0.002


def _circle(T0: torch.Tensor, t: float, radius: float, turn: float = 0.0) -> torch.Tensor:
    """T0 moved on a circle in its base y-z plane (0.5 Hz) and turned about its z axis by turn sin(πt/2)."""
    T = T0.clone()
    w = 2 * math.pi * 0.5
    T[1, 3] += radius * math.sin(w * t)
    T[2, 3] += radius * (1 - math.cos(w * t))
    if turn:
        a = turn * math.sin(math.pi * t / 2)
        c, s = math.cos(a), math.sin(a)
        Rz = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=T.dtype)
        T[:3, :3] = T0[:3, :3] @ Rz
    return T


def _margins(chain, q: torch.Tensor) -> float:
    """The smallest distance of a limited coordinate of q to its nearer limit."""
    lim = chain.q_limits
    finite = torch.isfinite(lim).all(-1)
    lo, hi = lim[finite, 0], lim[finite, 1]
    return float(torch.minimum(q[finite] - lo, hi - q[finite]).min())


def run(robot: str = "panda", seconds: float = 4.0, realtime: bool = False) -> dict:
    """One teleoperation run; returns the step times (µs), the worst limit margin, the largest |q̇|/q̇_max
    and the final tracking error (m)."""
    steps = int(round(seconds / DT))
    if robot == "panda":
        chain = from_mjcf(PANDA, "hand", dtype=torch.float64).requires_grad_(False)
        q = torch.tensor([0.0, -0.4, 0.0, -2.2, 0.0, 1.9, 0.8], dtype=torch.float64)
        vmax = torch.full((chain.nv,), 2.0, dtype=torch.float64)
        velocity = 2.0
        T0 = chain.forward_kinematics(q)
        hands, feet = [(0, T0)], []
        radius, turn = 0.05, 0.3
    elif robot == "g1":
        ends = ["left_foot", "right_foot", "left_elbow_roll_link", "right_elbow_roll_link"]
        chain = from_mjcf(G1, ends, dtype=torch.float64).requires_grad_(False)
        q = chain.neutral_configuration()
        q[2] = 0.755  # the pelvis at its MJCF height; knees and elbows bent (away from the singular stretch)
        bent = {"hip_pitch": -0.3, "knee": 0.6, "ankle_pitch": -0.3, "elbow_pitch": 1.0}
        for i, name in enumerate(chain.joint_names[1:]):
            q[7 + i] = next((a for key, a in bent.items() if key in name), 0.0)
        vmax = torch.full((chain.nv,), 4.0, dtype=torch.float64)
        vmax[:6] = math.inf  # the floating base: no limit
        velocity = {name: 4.0 for name, kind in zip(chain.joint_names, chain.joint_kinds) if kind != "free"}
        T = chain.forward_kinematics(q)
        feet, hands = [(0, T[0]), (1, T[1])], [(2, T[2]), (3, T[3])]
        radius, turn = 0.08, 0.0
    else:
        raise ValueError(f"robot must be 'panda' or 'g1', got {robot!r}")
    posture = ik.PostureTask(q.clone(), cost=1e-2)
    limits = (ik.ConfigurationLimit(gain=0.95), ik.VelocityLimit(velocity))
    fixed = [ik.FrameTask(k, target=T, lm_damping=1e-3) for k, T in feet]
    # the operator's input, one pose per hand and tick (a device would deliver them as the loop runs)
    inputs = [[_circle(T, (i + 1) * DT, radius, turn) for _, T in hands] for i in range(steps)]
    times, solves, margin, speed = [], [], math.inf, 0.0
    space = chain.configuration_space  # q ⊕ v (chain.integrate without its input checks)
    with torch.no_grad():
        for i in range(steps):
            t0 = time.perf_counter_ns()
            moving = [ik.FrameTask(k, target=T, lm_damping=1e-3) for (k, _), T in zip(hands, inputs[i])]
            v = ik.solve_velocity(chain, q, [*fixed, *moving, posture], DT, limits=limits)
            t1 = time.perf_counter_ns()
            q = space.integrate(q, v * DT)
            times.append((time.perf_counter_ns() - t0) / 1e3)
            solves.append((t1 - t0) / 1e3)
            margin = min(margin, _margins(chain, q))
            speed = max(speed, float((v.abs() / vmax).max()))
            if realtime:
                time.sleep(max(0.0, DT - times[-1] / 1e6))
        T = chain.forward_kinematics(q)
        T = T[None] if T.ndim == 2 else T
        err = max(float((T[k, :3, 3] - _circle(T_k, steps * DT, radius, turn)[:3, 3]).norm())
                  for k, T_k in hands)
        drift = max((float((T[k, :3, 3] - T_k[:3, 3]).norm()) for k, T_k in feet), default=0.0)
    p = np.percentile(times, [50, 90, 99, 100])
    return dict(robot=robot, steps=steps, nv=chain.nv, p50_us=p[0], p90_us=p[1], p99_us=p[2], max_us=p[3],
                solve_p50_us=float(np.median(solves)),
                within_budget=float(np.mean(np.array(times) < DT * 1e6)), worst_limit_margin=margin,
                max_speed_ratio=speed, final_tracking_error_m=err, feet_drift_m=drift)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--robot", choices=("panda", "g1", "both"), default="both")
    p.add_argument("--seconds", type=float, default=4.0)
    p.add_argument("--realtime", action="store_true")
    args = p.parse_args(argv)
    for robot in (("panda", "g1") if args.robot == "both" else (args.robot,)):
        r = run(robot, args.seconds, args.realtime)
        print(f"{robot} (nv {r['nv']}), {r['steps']} ticks at 500 Hz: tick p50 {r['p50_us']:.1f} µs "
              f"(solve_velocity {r['solve_p50_us']:.1f} µs), p90 {r['p90_us']:.1f} µs, "
              f"p99 {r['p99_us']:.1f} µs, "
              f"max {r['max_us']:.0f} µs ({100 * r['within_budget']:.1f} % within the 2 ms tick)")
        print(f"  worst joint-limit margin {r['worst_limit_margin']:.4f} (rad or m; < 0: a violation), "
              f"max |q̇|/q̇_max {r['max_speed_ratio']:.3f}, "
              f"final tracking error {1e3 * r['final_tracking_error_m']:.2f} mm"
              + (f", feet drift {1e3 * r['feet_drift_m']:.3f} mm" if robot == "g1" else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

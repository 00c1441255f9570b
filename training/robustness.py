"""Trained policies on perturbed robots: the kinematic domain-randomisation check.

    python -m diffkin.training.robustness RUN_DIR [RUN_DIR ...] --geometry-noise-length 0.02
        --geometry-noise-angle 0.04 [--robots 100] [--seed 20000] [--out docs/rl/dr_robustness.json]

Every run's deterministic policy is evaluated on the same ``robots`` episodes twice: on the nominal robot and
with every episode on its own robot, DH lengths and angles drawn uniformly within the given noise of nominal
(the env option :class:`~diffkin.envs.robot.RobotConfig` ``geometry_noise_length`` / ``_angle``; the
same seed gives the same robots, goals and start poses for every run). The scripted IK baseline, which
steers with the nominal model's Jacobian on the perturbed robot, is evaluated alongside.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from diffkin.training.evaluate import evaluate_run

__all__ = ["robustness", "main"]


def robustness(run_dirs, geometry_noise_length: float, geometry_noise_angle: float, robots: int = 100,
               seed: int = 20_000) -> dict:
    """``{"robots", "seed", "geometry_noise_length", "geometry_noise_angle", "runs": [...]}``: per run its
    policy's and the scripted baseline's success on the nominal and on the perturbed robots."""
    noise = {"geometry_noise_length": geometry_noise_length, "geometry_noise_angle": geometry_noise_angle}
    out = {"robots": robots, "seed": seed, **noise, "runs": []}
    for run in run_dirs:
        nominal = evaluate_run(run, robots, seed, robot_config=dict.fromkeys(noise, 0.0))  # a DR run too
        perturbed = evaluate_run(run, robots, seed, robot_config=noise)
        out["runs"].append({"run": str(run), "robot_config": perturbed["robot_config"],
                            "nominal": nominal["policy"], "perturbed": perturbed["policy"],
                            "scripted_ik_nominal": nominal["scripted_ik"],
                            "scripted_ik_perturbed": perturbed["scripted_ik"]})
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("run_dirs", nargs="+")
    p.add_argument("--geometry-noise-length", type=float, required=True, help="m, on the DH a and d")
    p.add_argument("--geometry-noise-angle", type=float, required=True, help="rad, on the DH alpha and theta")
    p.add_argument("--robots", type=int, default=100)
    p.add_argument("--seed", type=int, default=20_000)
    p.add_argument("--out", default=None, help="write the result as JSON there")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    res = robustness(args.run_dirs, args.geometry_noise_length, args.geometry_noise_angle, args.robots,
                     args.seed)
    text = json.dumps(res, indent=2)
    if args.out:
        Path(args.out).write_text(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

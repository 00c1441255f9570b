"""IK inside a training loop: a network that chooses target orientations, trained through ``ik.solve``.

Task: for a desired gripper position p, any orientation will do, but the arm should end up near a
comfortable rest posture and away from its joint limits. A small MLP maps p to an orientation (6D
representation -> rotation); the pose [R(p), p] goes through the batched IK solver, and the loss is on the
joint solution q*(p): its distance to the rest posture in units of each joint's range. The gradient reaches
the network through the solver by the implicit function theorem (dq* = J⁺ dx at the solution;
:mod:`diffkin.ik.implicit`) — no unrolled iterations.

Usage: ``python examples/ik_layer_posture.py [--steps 150] [--batch 256] [--seed 0]`` — prints the held-out
posture cost and IK success before and after training (about a minute on one CPU core).
"""

from __future__ import annotations

import argparse
import time

import torch
from torch import nn

from diffkin import ik, models


def rotation_from_6d(x: torch.Tensor) -> torch.Tensor:
    """Gram–Schmidt of two 3-vectors (Zhou et al. 2019) -> rotation matrix ``(..., 3, 3)``."""
    a = nn.functional.normalize(x[..., :3], dim=-1)
    b = nn.functional.normalize(x[..., 3:] - (a * x[..., 3:]).sum(-1, keepdim=True) * a, dim=-1)
    return torch.stack((a, b, torch.linalg.cross(a, b)), dim=-1)


def poses(p: torch.Tensor, net: nn.Module) -> torch.Tensor:
    R = rotation_from_6d(net(p))
    top = torch.cat((R, p.unsqueeze(-1)), dim=-1)
    bottom = torch.tensor([0.0, 0.0, 0.0, 1.0]).expand(*p.shape[:-1], 1, 4)
    return torch.cat((top, bottom), dim=-2)


def posture_cost(chain, q: torch.Tensor) -> torch.Tensor:
    lo, hi = chain.lower_upper()
    rest = 0.5 * (lo + hi)
    return (((q - rest) / (hi - lo)) ** 2).sum(-1)


def evaluate(chain, net, p) -> tuple[float, float]:
    with torch.no_grad():
        res = ik.solve(chain, poses(p, net), q0=0.5 * sum(chain.lower_upper()), seed=0)
    ok = res.success
    return float(posture_cost(chain, res.q)[ok].mean()), float(ok.float().mean())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=150)
    ap.add_argument("--batch", type=int, default=256)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    torch.manual_seed(args.seed)
    chain = models.load("panda").requires_grad_(False)  # the robot is fixed; only the network learns
    g = torch.Generator().manual_seed(args.seed)
    with torch.no_grad():  # reachable positions: FK of random configurations
        p_train = chain.forward_kinematics(chain.random_configuration(4096, generator=g))[..., :3, 3]
        p_test = chain.forward_kinematics(chain.random_configuration(512, generator=g))[..., :3, 3]
    net = nn.Sequential(nn.Linear(3, 64), nn.Tanh(), nn.Linear(64, 64), nn.Tanh(), nn.Linear(64, 6))
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    rest = 0.5 * sum(chain.lower_upper())
    before = evaluate(chain, net, p_test)
    t0 = time.perf_counter()
    for step in range(args.steps):
        p = p_train[torch.randint(len(p_train), (args.batch,), generator=g)]
        res = ik.solve(chain, poses(p, net), q0=rest, seed=step)  # q carries gradients to the poses
        ok = res.success
        loss = posture_cost(chain, res.q)[ok].mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        if step % 25 == 0 or step == args.steps - 1:
            print(f"step {step:4d}  posture cost {loss.item():.4f}  success {ok.float().mean():.3f}")
    after = evaluate(chain, net, p_test)
    print(f"\ntraining: {time.perf_counter() - t0:.1f} s for {args.steps} steps of {args.batch} IK solves")
    print("held-out positions (512)        | posture cost (mean) | IK success")
    print(f"untrained network orientations | {before[0]:19.4f} | {before[1] * 100:9.1f} %")
    print(f"trained through ik.solve       | {after[0]:19.4f} | {after[1] * 100:9.1f} %")
    return 0 if after[0] < before[0] else 1


if __name__ == "__main__":
    raise SystemExit(main())

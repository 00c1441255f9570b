"""IK as a differentiable layer: the cost of the implicit backward relative to the forward solve.

    python -m benchmarks.bench_ik_grad [--targets 10000] [--dtype float32] [--threads 1] [--quick]

Panda (``models.load("panda")``), random reachable full-pose targets at 0.1 mm / 1 mrad. Rows: the forward
``ik.solve`` with the target requiring grad (the iterations run without autograd either way), the backward of
a loss on the joint solution (gradients w.r.t. the targets and every chain parameter, or the targets only
with the chain frozen), their ratio, and the same for ``ik.optimize`` (pose + rest-posture cost, implicit
Hessian backward). Medians of repeated runs; the forward includes attaching the graph.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from benchmarks.common import print_table, torch_threads
from diffkin import ik, models

__all__ = ["run", "main"]


def _median_time(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def run(args=None) -> list[dict]:
    args = args if args is not None else parse_args([])
    quick = getattr(args, "quick", False)
    N = getattr(args, "targets", None) or (2_000 if quick else 10_000)
    dtype = {"float32": torch.float32, "float64": torch.float64}[getattr(args, "dtype", None) or "float32"]
    threads = getattr(args, "threads", None) or 1
    repeats = 3 if quick else 5
    with torch_threads(threads):
        chain = models.load("panda", dtype=dtype, learnable=True)
        q_true = chain.random_configuration((N,), generator=torch.Generator().manual_seed(0))
        with torch.no_grad():
            T = chain.forward_kinematics(q_true)
        q_rest = 0.5 * sum(chain.lower_upper())
        rows = []
        frozen = models.load("panda", dtype=dtype)  # the default: geometry frozen
        for name, solve in (
            ("solve (grads: targets + DH table, base, tool)", lambda Tg: ik.solve(chain, Tg, seed=1)),
            ("solve (grads: targets, chain frozen)", lambda Tg: ik.solve(frozen, Tg, seed=1)),
            ("optimize (pose + rest, L-BFGS 20)", lambda Tg: ik.optimize(
                chain, Tg, q0=q_true[: Tg.shape[0]], max_iterations=20,
                costs=[ik.PoseCost(), ik.RestPostureCost(weight=1e-3)])),
        ):
            if name.startswith("optimize") and N > 2_000:
                Tn = T[:2_000]
            else:
                Tn = T
            state = {}

            def forward(Tn=Tn, solve=solve, state=state):
                Tg = Tn.clone().requires_grad_(True)
                state["res"], state["T"] = solve(Tg), Tg

            def backward(state=state):
                loss = (state["res"].q - q_rest).square().sum()
                chain.zero_grad(set_to_none=True)
                loss.backward()

            forward()
            t_fwd, t_bwd = [], []
            for _ in range(repeats):
                t_fwd.append(_median_time(forward, 1))
                t_bwd.append(_median_time(backward, 1))
            f, b = statistics.median(t_fwd), statistics.median(t_bwd)
            ok = float(state["res"].success.float().mean())
            finite = bool(torch.isfinite(state["T"].grad).all())
            rows.append({"benchmark": "ik_grad", "impl": f"diffkin {name}", "dtype": str(dtype)[6:],
                         "targets": Tn.shape[0], "success": ok, "forward_s": f, "backward_s": b,
                         "backward_over_forward": b / f, "grads_finite": finite, "threads": threads})
    return rows


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--targets", type=int, default=None)
    p.add_argument("--dtype", choices=["float32", "float64"], default=None)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--quick", action="store_true")
    return p.parse_args(argv)


def main(argv=None) -> int:
    print_table(run(parse_args(argv)), "IK backward vs forward")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Geometric Jacobian speed: diffkin vs pytorch-kinematics on the same Panda, and FK + J vs FK alone.

    python -m benchmarks.bench_jacobian [--batch 1 1000 100000] [--threads 1] [--device cpu] [--quick]

Panda to the flange (panda_link8): diffkin's modified-DH model ``models.load("panda")`` and
pytorch-kinematics's serial chain from ``diffkin/models/data/panda.urdf``; float32, no autograd, the same
random joint batch for both. Each figure is the median over ``--repeats`` timed blocks of at least
``--min-time`` seconds (after a warm-up call). Rows report seconds per call, Jacobians per second, and
the ratios pk / diffkin and (diffkin FK + J) / (diffkin FK).
"""

from __future__ import annotations

import argparse

import torch

from benchmarks.common import pk_panda, timeit
from diffkin import models
from diffkin.jacobian import forward_kinematics_and_jacobian, geometric_jacobian

__all__ = ["run", "main"]

PEER_MAX_BATCH = 1000  # the peers loop in Python/C++ one configuration at a time: rates scale linearly


def _peer_rows(B: int, t_pk: float, common: dict, repeats: int) -> list[dict]:
    """Pinocchio and Robotics Toolbox Jacobians (float64, CPU; skipped when not installed)."""
    from benchmarks import peers

    m = min(B, PEER_MAX_BATCH)
    chain = models.load("panda", dtype=torch.float64)
    q = chain.random_configuration((m,), generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        J_ref = geometric_jacobian(chain, q).numpy()
    rows = []
    for name, fn in (("pinocchio computeFrameJacobian (Python loop)", peers.pinocchio_jacobian_rate),
                     ("robotics_toolbox ETS_jacob0 (C++)", peers.rtb_jacobian_rate)):
        try:
            rate, J = fn(q.numpy(), repeats=repeats)
        except peers.SkipPeer as e:
            print(f"[jacobian] {e}")
            continue
        rows.append({**common, "dtype": "float64", "impl": name, "seconds": B / rate,
                     "max_abs_diff_vs_diffkin": float(abs(J - J_ref).max()), "timed_batch": m,
                     "speedup_vs_pk": t_pk / (B / rate)})
    return rows


def bench_batch(B: int, chain, pk_chain, min_time: float, repeats: int, device: str, seed: int = 0):
    q = chain.random_configuration((B,), generator=torch.Generator().manual_seed(seed)).to(device)

    def timed(fn):
        return timeit(fn, min_time=min_time, repeats=repeats, device=device, warmup=1)

    with torch.no_grad():
        t_fk = timed(lambda: chain.forward_kinematics(q))
        t_j = timed(lambda: geometric_jacobian(chain, q))
        t_fkj = timed(lambda: forward_kinematics_and_jacobian(chain, q))
        t_pk = timed(lambda: pk_chain.jacobian(q))
        err = float((geometric_jacobian(chain, q) - pk_chain.jacobian(q)).abs().max())
    common = {"benchmark": "jacobian", "robot": "panda", "device": device, "dtype": "float32", "batch": B}
    rows = [
        {**common, "impl": "diffkin forward_kinematics", "seconds": t_fk},
        {**common, "impl": "diffkin geometric_jacobian", "seconds": t_j, "ratio_pk_over_diffkin": t_pk / t_j,
         "max_abs_diff_vs_pk": err},
        {**common, "impl": "diffkin forward_kinematics_and_jacobian", "seconds": t_fkj,
         "ratio_fkj_over_fk": t_fkj / t_fk},
        {**common, "impl": "pytorch_kinematics jacobian", "seconds": t_pk},
    ]  # fmt: skip
    if B > 1 and device == "cpu":
        rows += _peer_rows(B, t_pk, common, repeats)
    for r in rows:
        r["per_second"] = B / r["seconds"]
    return rows


def run(args=None) -> list[dict]:
    """Rows ``{benchmark, impl, batch, seconds, per_second, ...}`` for every batch size."""
    args = args if args is not None else parse_args([])
    quick = getattr(args, "quick", False)
    batches = getattr(args, "batch", None) or ([1, 1000, 10000] if quick else [1, 1000, 100000])
    device, threads = getattr(args, "device", "cpu"), getattr(args, "threads", 1)
    min_time = getattr(args, "min_time", None) or (0.05 if quick else 0.3)
    repeats = getattr(args, "repeats", None) or (3 if quick else 5)
    old = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        chain = models.load("panda", dtype=torch.float32).to(device)
        pk_chain = pk_panda(torch.float32, device)
        rows = []
        for B in batches:
            rows += bench_batch(B, chain, pk_chain, min_time, repeats, device)
    finally:
        torch.set_num_threads(old)
    for r in rows:
        r["threads"] = threads
    return rows


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--batch", type=int, nargs="+", default=None, help="batch sizes (default 1 1000 100000)")
    p.add_argument("--threads", type=int, default=1, help="torch intra-op threads (1: fairest on a busy box)")
    p.add_argument("--device", default="cpu")
    p.add_argument("--repeats", type=int, default=None, help="timed blocks per figure (default 5)")
    p.add_argument("--min-time", type=float, default=None, help="seconds per timed block (default 0.3)")
    p.add_argument("--quick", action="store_true")
    return p.parse_args(argv)


def main(argv=None) -> int:
    rows = run(parse_args(argv))
    print(f"{'impl':<42}{'batch':>8}{'ms/call':>11}{'M/s':>9}{'ratio':>16}")
    for r in rows:
        if "ratio_pk_over_diffkin" in r:
            ratio = f"pk/dk {r['ratio_pk_over_diffkin']:.1f}x"
        elif "ratio_fkj_over_fk" in r:
            ratio = f"(FK+J)/FK {r['ratio_fkj_over_fk']:.2f}"
        else:
            ratio = ""
        ms, rate = r["seconds"] * 1e3, r["per_second"] / 1e6
        print(f"{r['impl']:<42}{r['batch']:>8}{ms:>11.3f}{rate:>9.3f}{ratio:>16}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

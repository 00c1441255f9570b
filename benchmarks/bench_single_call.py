"""Single-call latency and batched IK throughput of the C solve (issue 28), side by side in one run.

* single-target ``ik.solve`` (Panda, float64, 1 thread, 0.1 mm / 1 mrad within the limits, random targets,
  one call each): median per call, against Robotics Toolbox's C++ ``ik_LM`` on the same targets (success
  checked independently by :func:`benchmarks.bench_ik.verify`). Two chain states: the default, parameters
  frozen (the lean path: one foreign call, ``dk_solve_one``; with ``seed=`` it draws the random seeds
  itself, only those it uses), and a learnable chain (``learnable=True``: the C solve plus the
  implicit-gradient attachment); and the lean path without ``seed=`` (the pool from torch's default
  generator);
* batch-1 FK and FK + Jacobian (the lean path, ``torch.no_grad()``), median per call, against Pinocchio's
  and Robotics Toolbox's C++ calls of one configuration in the same run;
* batched ``ik.solve`` of N Panda targets on 1 and 2 threads by its two backends, one algorithm: the C solve
  (``dk_solve``) and the torch backend (what CUDA runs), interleaved repeats: the time ratio, and whether
  both gave the same flags, iterations and q.

    python -m benchmarks.bench_single_call [--targets 200] [--batch 10000] [--repeats 3]
    python -m benchmarks.run single_call [--quick]
"""

from __future__ import annotations

import argparse
import statistics
import time
import warnings

import numpy as np
import torch

from benchmarks import peers
from benchmarks.bench_ik import TOL_O, TOL_P, make_targets, verify
from benchmarks.common import print_table, torch_threads
from diffkin import ik, models


def _median_us(fn, items) -> tuple[float, list]:
    times, out = [], []
    for it in items:
        t0 = time.perf_counter()
        out.append(fn(it))
        times.append(time.perf_counter() - t0)
    return statistics.median(times) * 1e6, out


def single_target(n: int) -> list[dict]:
    _, T = make_targets(n, seed=1)
    rows = []
    for label, frozen in (("lean path (default chain, params frozen)", True),
                          ("learnable chain (grad attached)", False)):
        chain = models.load("panda", dtype=torch.float64, learnable=not frozen)
        ik.solve(chain, T[0], seed=0)  # warm-up (the per-chain state)
        us, res = _median_us(lambda i, c=chain: ik.solve(c, T[i], seed=i), range(n))
        q = torch.stack([r.q.detach() for r in res])
        flags = torch.stack([r.success for r in res])
        rows.append({"case": f"ik.solve 1 target, {label}", "median_us": us, **verify(q, T, flags)})
        if frozen:  # no seed: the pool from torch's default generator (drawn whole, as the general path)
            us, res = _median_us(lambda i, c=chain: ik.solve(c, T[i]), range(n))
            q = torch.stack([r.q for r in res])
            flags = torch.stack([r.success for r in res])
            rows.append({"case": "ik.solve 1 target, lean path, no seed (torch's default generator)",
                         "median_us": us, **verify(q, T, flags)})
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            peers.rtb_panda()
    except Exception as e:  # optional peer
        print(f"[single] Robotics Toolbox skipped: {e!r}")
        return rows
    sols = [peers.rtb_ik_lm(T[i : i + 1].numpy()) for i in range(n)]  # its tuned settings, one pose a call
    q = torch.from_numpy(np.concatenate([s.q for s in sols]))
    us = statistics.median(s.seconds for s in sols) * 1e6
    rows.append({"case": "RTB ik_LM (C++), 1 target", "median_us": us, **verify(q, T)})
    return rows


def _peer_single_calls() -> list[tuple[str, object]]:
    """Pinocchio's and Robotics Toolbox's one-configuration calls on a numpy row (each returns what diffkin
    returns: the flange pose, and with the Jacobian the pose and J in the base frame)."""
    calls = []
    try:
        import pinocchio as pin

        model, data, fid = peers.pinocchio_panda()
        fk, ufp = pin.forwardKinematics, pin.updateFramePlacement
        cfj, frame = pin.computeFrameJacobian, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED

        def pin_fk(qi):
            fk(model, data, qi)
            return ufp(model, data, fid).homogeneous

        def pin_fkj(qi):
            J = cfj(model, data, qi, fid, frame)  # runs the joint FK itself
            return ufp(model, data, fid).homogeneous, J

        calls += [("Pinocchio FK, 1 configuration", pin_fk),
                  ("Pinocchio FK + Jacobian, 1 configuration", pin_fkj)]
    except Exception as e:  # optional peer
        print(f"[single] Pinocchio skipped: {e!r}")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ets = peers.rtb_panda()
        jac = peers._jacob0_fn(ets)
        calls += [("RTB FK (C++ ETS.eval), 1 configuration", ets.eval),
                  ("RTB FK + Jacobian (C++), 1 configuration", lambda qi: (ets.eval(qi), jac(qi)))]
    except Exception as e:  # optional peer
        print(f"[single] Robotics Toolbox skipped: {e!r}")
    return calls


def batch_one_kinematics(n: int = 2000) -> list[dict]:
    chain = models.load("panda", dtype=torch.float64)
    qb = chain.random_configuration((n,), generator=torch.Generator().manual_seed(2))
    qs, rows_np = qb.unbind(0), list(qb.numpy())
    rows = []
    with torch.no_grad():
        for case, fn in (("FK, 1 configuration", chain.forward_kinematics),
                         ("FK + Jacobian, 1 configuration", chain.forward_kinematics_and_jacobian)):
            fn(qs[0])
            us, _ = _median_us(fn, qs)
            rows.append({"case": case, "median_us": us})
    for case, fn in _peer_single_calls():
        for qi in rows_np[:50]:
            fn(qi)
        us, _ = _median_us(fn, rows_np)
        rows.append({"case": case, "median_us": us})
    return rows


def batched(N: int, repeats: int, threads: int) -> list[dict]:
    """ik.solve of N targets by its two backends (one algorithm): the C solve and the torch backend (what
    CUDA runs; here on the CPU under ``native.disabled()``), interleaved repeats of the same call."""
    from diffkin.kernels import native

    _, T = make_targets(N, seed=3)
    chain = models.load("panda", dtype=torch.float64)
    ik.solve(chain, T[:64], seed=0)
    times = {"C backend (dk_solve)": [], "torch backend": []}
    checks, results = {}, {}
    with torch_threads(threads), torch.no_grad():
        for rep in range(repeats):  # interleaved: both see the same machine load
            for name in times:
                t0 = time.perf_counter()
                if name.startswith("C"):
                    res = ik.solve(chain, T, seed=rep)
                else:
                    with native.disabled():
                        res = ik.solve(chain, T, seed=rep)
                times[name].append(time.perf_counter() - t0)
                checks[name], results[name] = verify(res.q.detach(), T, res.success), res
    c, t = results.values()
    same = {"same_flags": bool(torch.equal(c.success, t.success)),
            "same_iterations": bool(torch.equal(c.iterations, t.iterations)),
            "max_dq": float((c.q - t.q).abs().max()) if N else 0.0}
    rows = []
    for name, ts in times.items():
        s = statistics.median(ts)
        res = results[name]
        rows.append({"case": f"ik.solve {N} targets, {threads} thread(s), {name}", "median_us": s * 1e6,
                     "solves_per_s": N / s, "mean_iterations": float(res.iterations.float().mean()),
                     **checks[name]})
    rows[0].update(same, ratio_vs_torch=rows[1]["median_us"] / rows[0]["median_us"])
    return rows


def run(args) -> list[dict]:
    """The rows of all three parts (``benchmarks.run`` interface; ``targets``, ``batch``, ``repeats`` and
    ``calls`` (batch-1 FK calls) default by ``quick``)."""
    quick = getattr(args, "quick", False)
    n = getattr(args, "targets", None) or (20 if quick else 200)
    N = getattr(args, "batch", None) or (1000 if quick else 10000)
    repeats = getattr(args, "repeats", None) or (1 if quick else 3)
    calls = getattr(args, "calls", None) or (200 if quick else 2000)
    with torch_threads(1):
        rows = single_target(n) + batch_one_kinematics(calls)
    rows += batched(N, repeats, 1) + batched(N, repeats, 2)
    return [{"benchmark": "single calls and batched IK", **r} for r in rows]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--targets", type=int, default=200)
    p.add_argument("--batch", type=int, default=10000)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--only-fk", action="store_true", help="only the batch-1 FK and FK + Jacobian rows")
    a = p.parse_args(argv)
    if a.only_fk:
        with torch_threads(1):
            print_table(batch_one_kinematics(), "batch-1 kinematics (medians; one run, same machine load)")
        return 0
    print(f"tolerances {TOL_P} m / {TOL_O} rad, float64, Panda")
    print_table(run(a), "single calls and batched IK (medians; one run, same machine load)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

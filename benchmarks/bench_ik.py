"""Batched IK on random reachable Panda poses: diffkin.ik.solve vs pytorch-kinematics and Robotics Toolbox.

    python -m benchmarks.bench_ik [--targets 10000] [--quick] [--threads 1] [--device cpu] [--repeats 3]
                                  [--no-rtb] [--pk-configs fast accurate] [--compile] [--backends]

Targets: FK of joints drawn uniformly within the Panda's limits (fixed seed), full 6-D poses, tolerances
0.1 mm and 1e-3 rad for every solver. Every solution is re-checked here with a float64 FK (position error,
rotation angle of R_eᵀR_d) and against the joint limits (1e-6 rad slack for float32 rounding of the limits),
so "success" does not depend on a solver's own flags. Times are wall-clock seconds for the whole batch
(median over ``--repeats`` runs for diffkin; pytorch-kinematics and RTB once each, they are slow), and the
process CPU seconds next to them (less sensitive to other jobs on a shared machine); solves/s = targets /
seconds; ``speedup_vs_pk`` (and ``_cpu``) is against pytorch-kinematics's fastest configuration in the
same run.

pytorch-kinematics ``PseudoInverseIK`` (float32, its default dtype) in two configurations from a sweep of
num_retries x max_iterations x lr x lm_damping at these tolerances: ``fast`` = 10 retries, 50 iterations,
lr 1.0 (default lm_damping 0.1, joint limits given, early stopping on convergence and on no improvement);
``accurate`` = 20 retries, 30 iterations (``--compile`` adds ``fast`` with ``use_compile=True``, timed
after a compiling warm-up call on the same batch; ~1.2x faster here). Robotics Toolbox's C++ ``ik_LM``
(Chan damping, joint limits, 30 iterations x 100 searches, tol = E = ½‖e‖² ≤ 5e-9) solves one pose per
call, from the same URDF.

``--backends`` adds diffkin's two backends of the one LM schedule on the same float64 targets and seed (CPU):
the C solve, the torch loop (what CUDA runs, here under ``native.disabled()``) with the seeds in lockstep
rounds, and the torch loop with each target's seeds one after another (the schedule before the lockstep
rounds); ``ratio_to_c`` is each time over the C path's in the same run, ``same_as_c`` whether the success
flags, iterations and seeds tried are equal and q within 1e-6. Measured on 2 000 targets (2 shared cores,
contended, 1 thread), three runs: C 0.085 / 0.179 / 0.051 s, torch lockstep 2.19 / 5.72 / 0.77 s (26x /
32x / 15x the C path), torch one seed after another 6.24 / 12.56 / 2.05 s (73x / 70x / 41x); CPU seconds
of the last run 0.023, 0.38, 1.01. All three give the same answers (100 % success, flags honest).
"""

from __future__ import annotations

import argparse
import statistics
import time
import warnings

import torch

from benchmarks.common import PANDA_URDF, pk_panda, print_table, sync
from diffkin import models
from diffkin.ik.numerical import solve
from diffkin.ik.result import rotation_angle_between

__all__ = ["run", "main", "PK_CONFIGS"]

TOL_P, TOL_O, LIMIT_SLACK = 1e-4, 1e-3, 1e-6
PK_CONFIGS = {
    "fast": {"num_retries": 10, "max_iterations": 50, "lr": 1.0},
    "accurate": {"num_retries": 20, "max_iterations": 30, "lr": 1.0},
}


def make_targets(n: int, seed: int = 0):
    """``(q_true (n, 7), T (n, 4, 4))`` in float64 from uniform joints within the limits."""
    chain = models.load("panda", dtype=torch.float64)
    q = chain.random_configuration((n,), generator=torch.Generator().manual_seed(seed))
    with torch.no_grad():
        return q, chain.forward_kinematics(q)


def verify(q: torch.Tensor, T: torch.Tensor, flags: torch.Tensor | None = None) -> dict:
    """Independent float64 check of ``q (n, 7)`` against ``T (n, 4, 4)`` (and of a solver's own flags)."""
    chain = models.load("panda", dtype=torch.float64)
    q = q.detach().to("cpu", torch.float64)
    finite = torch.isfinite(q).all(-1)
    q = torch.where(finite[:, None], q, torch.zeros_like(q))
    with torch.no_grad():
        Te = chain.forward_kinematics(q)
    pe = torch.linalg.vector_norm(Te[:, :3, 3] - T[:, :3, 3], dim=-1)
    oe = rotation_angle_between(Te[:, :3, :3], T[:, :3, :3])
    ok = finite & (pe <= TOL_P) & (oe <= TOL_O)
    inlim = chain.within_limits(q, tol=LIMIT_SLACK)
    out = {"success": float(ok.double().mean()), "success_within_limits": float((ok & inlim).double().mean())}
    if flags is not None:  # every sample the solver calls a success really is one
        out["flags_honest"] = not bool((flags.cpu() & ~(ok & inlim)).any())
    return out


def _diffkin(T, dtype, device, repeats) -> dict:
    chain = models.load("panda", dtype=dtype, device=device)
    Td = T.to(device=device, dtype=dtype)
    times, cpu, checks, iters = [], [], [], []
    solve(chain, Td[:64], seed=123)  # warm-up
    for rep in range(repeats):
        sync(device)
        t0, c0 = time.perf_counter(), time.process_time()
        res = solve(chain, Td, seed=rep)
        sync(device)
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
        checks.append(verify(res.q, T, res.success))
        iters.append(float(res.iterations.double().mean()))
    worst = min(checks, key=lambda c: c["success_within_limits"])
    worst["flags_honest"] = all(c["flags_honest"] for c in checks)
    name = str(dtype).removeprefix("torch.")
    return {"impl": f"diffkin ({name})", "dtype": name, "seconds": statistics.median(times),
            "cpu_seconds": statistics.median(cpu), **worst,
            "mean_iterations": statistics.mean(iters)}  # fmt: skip


def _pk(T, config: str, device, compile: bool = False) -> dict:
    import pytorch_kinematics as pk

    ch = pk_panda(torch.float32, device)
    lim = torch.tensor(ch.get_joint_limits(), dtype=torch.float32, device=device).T
    ik = pk.PseudoInverseIK(ch, joint_limits=lim, pos_tolerance=TOL_P, rot_tolerance=TOL_O,
                            early_stopping_any_converged=True, early_stopping_no_improvement="all",
                            use_compile=compile, **PK_CONFIGS[config])  # fmt: skip
    goal = pk.Transform3d(matrix=T.to(device=device, dtype=torch.float32), device=device)
    if compile:
        ik.solve(goal)  # compile (tens of seconds) and warm up on the same batch
    sync(device)
    t0, c0 = time.perf_counter(), time.process_time()
    sol = ik.solve(goal)
    sync(device)
    dt, dc = time.perf_counter() - t0, time.process_time() - c0
    conv = sol.converged  # (n, retries): take the first converged retry, else retry 0
    first = torch.where(conv.any(1), conv.float().argmax(1), torch.zeros_like(conv[:, 0], dtype=torch.long))
    q = sol.solutions[torch.arange(T.shape[0], device=device), first]
    name = f"pk PseudoInverseIK {config}" + (" compiled" if compile else "")
    return {"impl": name, "dtype": "float32", "seconds": dt, "cpu_seconds": dc,
            **verify(q, T), **{f"pk_{k}": v for k, v in PK_CONFIGS[config].items()}}  # fmt: skip


def _rtb(T) -> dict | None:
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            import roboticstoolbox as rtb

            ets = rtb.Robot.URDF(str(PANDA_URDF)).ets(end="panda_link8")
    except Exception as e:  # optional reference
        print(f"[ik] Robotics Toolbox skipped: {e!r}")
        return None
    Tn = T.numpy()
    qs = torch.empty(T.shape[0], 7, dtype=torch.float64)
    t0, c0 = time.perf_counter(), time.process_time()
    for i in range(T.shape[0]):
        qs[i] = torch.from_numpy(ets.ik_LM(Tn[i], ilimit=30, slimit=100, tol=5e-9, joint_limits=True)[0])
    dt, dc = time.perf_counter() - t0, time.process_time() - c0
    return {"impl": "RTB ik_LM (C++, 1 pose/call)", "dtype": "float64", "seconds": dt, "cpu_seconds": dc,
            **verify(qs, T)}  # fmt: skip


def run(args=None) -> list[dict]:
    """Rows ``{benchmark, impl, targets, seconds, solves_per_s, success, success_within_limits, ...}``."""
    args = args if args is not None else parse_args([])
    quick = getattr(args, "quick", False)
    n = getattr(args, "targets", None) or (1000 if quick else 10000)
    device, threads = getattr(args, "device", "cpu"), getattr(args, "threads", 1)
    repeats = getattr(args, "repeats", None) or 3
    pk_configs = getattr(args, "pk_configs", None) or list(PK_CONFIGS)
    old = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        _, T = make_targets(n, seed=getattr(args, "seed", 0))
        rows = [_diffkin(T, dt, device, repeats) for dt in (torch.float32, torch.float64)]
        rows += [_pk(T, cfg, device) for cfg in pk_configs]
        if getattr(args, "compile", False):
            rows.append(_pk(T, "fast", device, compile=True))
        if not getattr(args, "no_rtb", False) and device == "cpu":
            r = _rtb(T)
            rows += [r] if r is not None else []
        if getattr(args, "backends", False):
            rows += _backends(T, repeats)
    finally:
        torch.set_num_threads(old)
    pk_rows = [r for r in rows if r["impl"].startswith("pk ")]
    t_pk = min(r["seconds"] for r in pk_rows) if pk_rows else None
    c_pk = min(r["cpu_seconds"] for r in pk_rows) if pk_rows else None
    out = []
    for r in rows:
        row = {"benchmark": "ik", "impl": r.pop("impl"), "targets": n, "device": device, "threads": threads}
        row.update(r)
        row["solves_per_s"] = n / row["seconds"]
        row["solves_per_cpu_s"] = n / row["cpu_seconds"]
        if t_pk is not None:
            row["speedup_vs_pk"] = t_pk / row["seconds"]
            row["speedup_vs_pk_cpu"] = c_pk / row["cpu_seconds"]
        out.append(row)
    return out


def _backends(T, repeats: int) -> list[dict]:
    """The C solve and the torch loop (lockstep, and one seed after another) on the same targets and seed."""
    from diffkin.ik import _lm
    from diffkin.kernels import native

    chain = models.load("panda", dtype=torch.float64)
    sequential = lambda *a, **k: _lm._run_sequential(*a, **k)  # noqa: E731

    def timed(mode):
        times, cpu, res = [], [], None
        for _ in range(repeats):
            t0, c0 = time.perf_counter(), time.process_time()
            with torch.no_grad():
                if mode == "c":
                    res = solve(chain, T, seed=1)
                else:
                    lockstep = _lm._run_lockstep
                    try:
                        if mode == "sequential":
                            _lm._run_lockstep = sequential
                        with native.disabled():
                            res = solve(chain, T, seed=1)
                    finally:
                        _lm._run_lockstep = lockstep
            times.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
        return res, statistics.median(times), statistics.median(cpu)

    solve(chain, T[:16], seed=1)  # warm-up (the C library)
    out, ref, t_c = [], None, None
    modes = (("c", "diffkin C solve (f64)"), ("lockstep", "diffkin torch LM, seeds in lockstep (f64)"),
             ("sequential", "diffkin torch LM, seeds one after another (f64)"))
    for mode, name in modes:
        res, t, c = timed(mode)
        ref, t_c = (res, t) if ref is None else (ref, t_c)
        same = bool(torch.equal(res.success, ref.success) and torch.equal(res.iterations, ref.iterations)
                    and torch.equal(res.seeds_tried, ref.seeds_tried)
                    and float((res.q - ref.q).abs().max()) <= 1e-6)
        out.append({"impl": name, "seconds": t, "cpu_seconds": c, **verify(res.q, T, res.success),
                    "ratio_to_c": t / t_c, "same_as_c": same})
    return out


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--targets", type=int, default=None, help="number of targets (default 10000, quick 1000)")
    p.add_argument("--quick", action="store_true")
    p.add_argument("--threads", type=int, default=1, help="torch intra-op threads (1: fairest on a busy box)")
    p.add_argument("--device", default="cpu")
    p.add_argument("--repeats", type=int, default=None, help="diffkin runs (median time; default 3)")
    p.add_argument("--seed", type=int, default=0, help="seed of the target joints")
    p.add_argument("--no-rtb", action="store_true", help="skip Robotics Toolbox")
    p.add_argument("--pk-configs", nargs="+", choices=list(PK_CONFIGS), default=None)
    p.add_argument("--compile", action="store_true", help="also time pk's use_compile=True (fast config)")
    p.add_argument("--backends", action="store_true",
                   help="also diffkin's C solve vs its torch LM (lockstep, and one seed after another)")
    return p.parse_args(argv)


def main(argv=None) -> int:
    rows = run(parse_args(argv))
    print_table(rows, title="IK: random reachable Panda poses, 0.1 mm / 1e-3 rad")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

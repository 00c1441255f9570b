"""Where one teleoperation step's time goes (issue 35, item 3): the C velocity step alone, timed in a C loop
(:file:`benchmarks/velocity_driver.c`, no Python around the call), the batch-1 FK + Jacobian alone
(``dk_fk_one``, the lean FK path's call, in the same C loop), the Python call
:meth:`~diffkin.ik._native_velocity.NativeVelocity.step` and the public ``ik.solve_velocity`` (the task
objects built beforehand), one Panda row of the bench_teleop loop (FrameTask + PostureTask +
ConfigurationLimit + VelocityLimit, the target on a 5 cm circle, Δt = 2 ms).

    python -m benchmarks.teleop_profile [--steps 2000] [--json out.json]

Medians of ``--steps`` steps; the machine may be shared: compare the rows of one run.
"""

from __future__ import annotations

import argparse
import ctypes
import shutil
import statistics
import subprocess
import tempfile
import time
from pathlib import Path

import torch

from benchmarks.bench_teleop import DT, LM, PANDA, POSTURE, Q0, VMAX, _targets
from benchmarks.common import cli

__all__ = ["run", "main"]

DRIVER = Path(__file__).with_name("velocity_driver.c")


def _driver(tmp: Path) -> ctypes.CDLL:
    cc = shutil.which("cc") or shutil.which("gcc") or shutil.which("clang")
    if cc is None:
        raise RuntimeError("no C compiler")
    out = tmp / "velocity_driver.so"
    subprocess.run([cc, "-O2", "-shared", "-fPIC", "-o", str(out), str(DRIVER)], check=True)
    lib = ctypes.CDLL(str(out))
    lib.loop.restype = ctypes.c_int64
    P, I64 = ctypes.c_void_p, ctypes.c_int64
    lib.loop.argtypes = [P, P, P, P, P, I64, P, P, ctypes.c_double, I64, P]
    lib.loop_fk.restype, lib.loop_fk.argtypes = ctypes.c_int64, [P, P, P, P, P, P, I64, P]
    return lib


def _median_us(times) -> float:
    return statistics.median(times) * 1e6


def run(args) -> list[dict]:
    from diffkin import ik
    from diffkin.ik._native_velocity import NativeVelocity
    from diffkin.kernels import single
    from diffkin.models import from_mjcf

    steps = 300 if getattr(args, "quick", False) else max(200, getattr(args, "steps", 2000))
    torch.set_num_threads(1)
    chain = from_mjcf(PANDA, "hand", dtype=torch.float64).requires_grad_(False)
    prob = NativeVelocity(chain, [(0, 1.0, 1.0, 1.0, LM)], posture=(POSTURE, 1.0, 0.0),
                          configuration_limit=(0.95, 0.0), velocity_limit=VMAX)
    q = torch.tensor(Q0, dtype=torch.float64)
    q_ref = q.clone()
    T0 = chain.forward_kinematics(q).numpy()
    tgt = torch.from_numpy(_targets(T0, steps)).contiguous()
    views = list(tgt)
    v = torch.empty(7, dtype=torch.float64)
    rows = []
    with torch.no_grad():
        prob.step(q, views[0], q_ref, DT, out=v)  # packs the chain and binds its Data
        lean = prob._entry
        with tempfile.TemporaryDirectory() as tmp:
            lib = _driver(Path(tmp))
            qs = [q.clone(), torch.empty_like(q)]
            times = (ctypes.c_double * steps)()
            step = ctypes.cast(lean[1], ctypes.c_void_p).value
            status = lib.loop(step, lean[2], qs[0].data_ptr(), qs[1].data_ptr(), tgt.data_ptr(), 16,
                              q_ref.data_ptr(), v.data_ptr(), DT, steps, times)
            if status:
                raise RuntimeError(f"dk_velocity_step failed ({status})")
            rows.append(dict(part="C step alone (dk_velocity_step in a C loop)", median_us=_median_us(times)))
            q_c = qs[steps % 2].clone()  # where the C loop ended: the Python loop below must end there too
            hit = lean[0]
            T, J = torch.empty(4, 4, dtype=torch.float64), torch.empty(6, 7, dtype=torch.float64)
            fk = ctypes.cast(single._fk_one(), ctypes.c_void_p).value
            status = lib.loop_fk(fk, hit.base, hit.watch_addr, q.data_ptr(), T.data_ptr(), J.data_ptr(),
                                 steps, times)
            if status:
                raise RuntimeError(f"dk_fk_one failed ({status})")
            rows.append(dict(part="FK + Jacobian alone (dk_fk_one in a C loop, 16 lanes; the step: 4)",
                             median_us=_median_us(times)))
        qs = [q.clone(), torch.empty_like(q)]
        py = []
        for k in range(steps):
            t0 = time.perf_counter()
            prob.step(qs[k % 2], views[k], q_ref, DT, out=v, next_q=qs[(k + 1) % 2])
            py.append(time.perf_counter() - t0)
        rows.append(dict(part="NativeVelocity.step (Python, one ctypes call)", median_us=_median_us(py),
                         max_abs_q_diff_vs_c_loop=float((qs[steps % 2] - q_c).abs().max())))
        limits = (ik.ConfigurationLimit(gain=0.95), ik.VelocityLimit(VMAX))
        posture = ik.PostureTask(q_ref, cost=POSTURE)
        tasks = [[ik.FrameTask(0, target=T, position_cost=1.0, orientation_cost=1.0, lm_damping=LM), posture]
                 for T in views]
        state, pub = q.clone(), []
        for k in range(steps):
            t0 = time.perf_counter()
            vk = ik.solve_velocity(chain, state, tasks[k], DT, limits=limits)
            pub.append(time.perf_counter() - t0)
            state = state + vk * DT
        rows.append(dict(part="ik.solve_velocity (tasks built beforehand)", median_us=_median_us(pub),
                         max_abs_q_diff_vs_c_loop=float((state - q_c).abs().max())))
    c = rows[0]["median_us"]
    for r in rows:
        r["ratio_to_c_step"] = r["median_us"] / c
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--steps", type=int, default=2000)
    return cli(p, run, "one teleoperation step, part by part (medians; one run)", argv)


if __name__ == "__main__":
    raise SystemExit(main())

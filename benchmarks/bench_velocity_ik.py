"""One velocity-IK step with hard limits: diffkin's batched ``ik.velocity_step`` against mink's ``solve_ik``.

    python -m benchmarks.bench_velocity_ik [--rows 4096] [--panda-xml PATH] [--threads 1] [--quick]
    python -m benchmarks.run velocity_ik

The problem, per row (Panda, float64): min ‖J q̇ − v‖² + λ‖q̇‖² under the joint position limits over
Δt and |q̇| ≤ q̇_max (issue 29's (V.1)–(V.2)), λ = 1e-3, Δt = 0.1 s, q̇_max = 1 rad/s, random q within the
limits and random twists v ~ N(0, I) (m/s, rad/s): on average 3–4 of the 7 bounds are active per row.

* ``diffkin``: one ``velocity_step`` call on all rows (and on one row, batch shape ()).
* ``mink``: ``mink.solve_ik(configuration, [task], dt, solver="daqp", damping=λ, limits=[ConfigurationLimit
  (gain 1), VelocityLimit])`` on the MuJoCo Menagerie Panda (tests/data/mjcf/franka_emika_panda/panda.xml,
  compiled without its mesh files), looped over the rows (``configuration.update(q)`` + ``solve_ik`` per
  row). The task is a ``mink.Task`` whose error is −v·Δt and whose Jacobian is MuJoCo's ``mj_jacBody`` of
  ``link8`` (the base-frame geometric Jacobian of the flange, diffkin's end link) so both libraries solve
  the same QP. (mink's own ``FrameTask`` uses the log-map pose error, which equals this only to first
  order in Δt.) The Menagerie model has two finger joints after the seven arm joints; their Jacobian
  columns are zero, so their velocity is 0 and the arm's joints map one to one.

Reported: the largest |J_diffkin − J_mujoco| over the rows (the models agree), time per row, the ratio
mink / diffkin, and the largest |q̇_diffkin − q̇_mink| (the solutions agree); for one row also the process
CPU time per call (robust to other processes sharing the cores). The machine is shared: medians.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.common import FULL, QUICK, timeit, torch_threads
from diffkin import ik, models

__all__ = ["run", "main"]

ROOT = Path(__file__).resolve().parents[1]
PANDA_XML = ROOT / "tests" / "data" / "mjcf" / "franka_emika_panda" / "panda.xml"
DT, DAMPING, VMAX = 0.1, 1e-3, 1.0
ARM = [f"joint{i}" for i in range(1, 8)]


def _menagerie_panda(path: Path):
    """The Menagerie Panda compiled by MuJoCo with its mesh geoms as small spheres (kinematics only)."""
    import mujoco

    spec = mujoco.MjSpec.from_file(str(path))
    for geom in spec.geoms:
        if geom.type == mujoco.mjtGeom.mjGEOM_MESH:
            geom.type, geom.meshname = mujoco.mjtGeom.mjGEOM_SPHERE, ""
            geom.size = [0.01, 0, 0]
    for mesh in list(spec.meshes):
        spec.delete(mesh)
    return spec.compile()


def _twist_task(mink, mujoco, model):
    """A mink task with error −v·Δt and the flange's world-aligned geometric Jacobian (see module doc)."""
    body = model.body("link8").id

    class TwistTask(mink.Task):
        def __init__(self):
            super().__init__(cost=np.ones(6), gain=1.0)
            self.twist = np.zeros(6)

        def compute_error(self, configuration):
            return -self.twist * DT

        def compute_jacobian(self, configuration):
            jp, jr = np.zeros((3, model.nv)), np.zeros((3, model.nv))
            mujoco.mj_jacBody(model, configuration.data, jp, jr, body)
            return np.vstack((jp, jr))

    return TwistTask()


def _mink_setup(path: Path):
    import mink
    import mujoco

    model = _menagerie_panda(path)
    conf = mink.Configuration(model)
    task = _twist_task(mink, mujoco, model)
    limits = [mink.ConfigurationLimit(model, gain=1.0), mink.VelocityLimit(model, dict.fromkeys(ARM, VMAX))]
    arm = [model.joint(n).qposadr[0] for n in ARM]

    def solve(q: np.ndarray, v: np.ndarray) -> np.ndarray:
        qpos = np.zeros(model.nq)
        qpos[arm] = q
        conf.update(qpos)
        task.twist = v
        return mink.solve_ik(conf, [task], DT, solver="daqp", damping=DAMPING, limits=limits)

    def jacobian(q: np.ndarray) -> np.ndarray:
        qpos = np.zeros(model.nq)
        qpos[arm] = q
        conf.update(qpos)
        return task.compute_jacobian(conf)[:, [model.joint(n).dofadr[0] for n in ARM]]

    return solve, jacobian


def _rows(chain, B: int):
    gen = torch.Generator().manual_seed(0)
    lo, hi = chain.q_limits[:, 0], chain.q_limits[:, 1]
    q = lo + (hi - lo) * (0.02 + 0.96 * torch.rand(B, 7, generator=gen, dtype=torch.float64))
    return q, torch.randn(B, 6, generator=gen, dtype=torch.float64)


def _cpu_time(fn, repeats: int, calls: int = 50) -> float:
    """Median process-CPU seconds per call over ``repeats`` blocks (robust to other processes)."""
    fn()
    per = []
    for _ in range(repeats):
        t0 = time.process_time()
        for _ in range(calls):
            fn()
        per.append((time.process_time() - t0) / calls)
    return statistics.median(per)


def _step(chain, q, v):
    return ik.velocity_step(chain, q, v, DT, damping=DAMPING, velocity_limit=VMAX)


def run(args) -> list[dict]:
    quick = getattr(args, "quick", False)
    B = 256 if quick else getattr(args, "rows", 4096)
    path = Path(getattr(args, "panda_xml", None) or PANDA_XML)
    min_time, repeats = QUICK if quick else FULL
    with torch_threads(getattr(args, "threads", 1)), torch.no_grad():
        chain = models.load("panda", dtype=torch.float64).requires_grad_(False)
        q, v = _rows(chain, B)
        t_batch = timeit(lambda: _step(chain, q, v), min_time, repeats)
        t_one = timeit(lambda: _step(chain, q[0], v[0]), min_time, repeats)
        cpu_one = _cpu_time(lambda: _step(chain, q[0], v[0]), repeats)
        qd = _step(chain, q, v).numpy()
        c32 = models.load("panda", dtype=torch.float32).requires_grad_(False)
        q32, v32 = q.float(), v.float()
        t_batch32 = timeit(lambda: _step(c32, q32, v32), min_time, repeats)
        J = chain.forward_kinematics_and_jacobian(q)[1].numpy()
    lo, hi = chain.q_limits[:, 0].numpy(), chain.q_limits[:, 1].numpy()
    active = ((np.abs(qd - np.clip((lo - q.numpy()) / DT, -VMAX, VMAX)) < 1e-12)
              | (np.abs(qd - np.clip((hi - q.numpy()) / DT, -VMAX, VMAX)) < 1e-12)).sum(-1).mean()
    rows = [dict(benchmark="velocity_ik_panda", impl="diffkin velocity_step (float64)", batch=B,
                 seconds=t_batch, us_per_row=1e6 * t_batch / B, mean_active_bounds=float(active)),
            dict(benchmark="velocity_ik_panda", impl="diffkin velocity_step (float32)", batch=B,
                 seconds=t_batch32, us_per_row=1e6 * t_batch32 / B),
            dict(benchmark="velocity_ik_panda", impl="diffkin velocity_step, one row", batch=1, seconds=t_one,
                 us_per_row=1e6 * t_one, cpu_us_per_row=1e6 * cpu_one)]
    if not path.exists():
        print(f"[velocity_ik] mink rows skipped: no Menagerie Panda at {path} (pass --panda-xml)")
        return rows
    solve, jacobian = _mink_setup(path)
    jac_diff = max(float(np.abs(jacobian(q[i].numpy()) - J[i]).max()) for i in range(min(B, 256)))
    per_block = []
    for _ in range(3 if quick else 5):
        t0 = time.perf_counter()
        out = np.stack([solve(q[i].numpy(), v[i].numpy()) for i in range(B)])
        per_block.append(time.perf_counter() - t0)
    t_mink = statistics.median(per_block)
    t_mink_one = timeit(lambda: solve(q[0].numpy(), v[0].numpy()), min_time, repeats)
    cpu_mink_one = _cpu_time(lambda: solve(q[0].numpy(), v[0].numpy()), repeats)
    agree = float(np.abs(out[:, :7] - qd).max())
    rows += [dict(benchmark="velocity_ik_panda", impl="mink solve_ik (daqp), looped", batch=B, seconds=t_mink,
                  us_per_row=1e6 * t_mink / B, ratio_mink_over_diffkin=t_mink / t_batch,
                  max_abs_qdot_diff=agree, max_finger_qdot=float(np.abs(out[:, 7:]).max()),
                  jacobian_max_diff=jac_diff),
             dict(benchmark="velocity_ik_panda", impl="mink solve_ik (daqp), one call", batch=1,
                  seconds=t_mink_one, us_per_row=1e6 * t_mink_one, cpu_us_per_row=1e6 * cpu_mink_one,
                  ratio_mink_over_diffkin=t_mink_one / t_one, cpu_ratio=cpu_mink_one / cpu_one)]
    return rows


def main(argv=None) -> int:
    from benchmarks.common import print_table

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rows", type=int, default=4096)
    p.add_argument("--panda-xml", default=None, help=f"Menagerie panda.xml (default {PANDA_XML})")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--quick", action="store_true")
    print_table(run(p.parse_args(argv)), "velocity_ik_panda")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

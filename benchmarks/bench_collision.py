"""Self-collision distances of the Franka FR3 (Panda's successor; Franka's own coarse self-collision model:
30 spheres and capsule-capped cylinders, 297 checked pairs): diffkin beside Pinocchio + coal, in one run.

    python -m benchmarks.bench_collision [--batch 1000 100000] [--peer-rows 2000] [--quick]

diffkin: ``RobotCollision.from_urdf(fr3.urdf, chain).self_distances(q)`` on one batch (FK of every link
frame included), under ``torch.no_grad()``, float32 and float64; ``+grad`` rows add the backward pass of
``min_distance(q).sum()`` to q. Pinocchio + coal: ``pinocchio.computeDistances`` (its FK, geometry
placements and coal's distance for the same 297 pairs, cylinders as the same capsules) looped over rows in
Python, float64, timed on ``--peer-rows`` rows (its cost is linear in rows), three times before and three
times after ours (the median, with the min and max). Rows: seconds per call
(median, :mod:`benchmarks.common`), microseconds per row and ``speedup_vs_pin_coal`` (its per-row time /
ours). MuJoCo: the same URDF through MuJoCo's compiler (meshes dropped, static bodies kept: the same 30
geoms, true cylinders), ``mj_kinematics`` + ``mj_collision`` looped over rows: contacts of penetrating pairs
only, after its bounding-volume broad phase, so a cheaper query than 297 signed distances (its pair set is
ours plus link 0 × link 1, which its parent filter keeps). The machine is shared: compare ratios from one
run.
"""

from __future__ import annotations

import argparse
import re
import statistics
import time
import warnings
from pathlib import Path

import torch

from benchmarks.common import FULL, QUICK, cli, timeit
from diffkin import models
from diffkin.collision import RobotCollision

__all__ = ["run", "main", "FR3_URDF"]

FR3_URDF = Path(__file__).resolve().parents[1] / "tests" / "data" / "urdf" / "fr3.urdf"


def _robot(dtype: torch.dtype, device: str):
    chain = models.from_urdf(FR3_URDF, "fr3_link8", dtype=dtype, device=device)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the meshes are not shipped; the sc primitives are the model
        return chain, RobotCollision.from_urdf(FR3_URDF, chain)


def _pin_coal(rc: RobotCollision):
    """(per-row seconds function of a (N, 7) float64 array) for Pinocchio + coal on rc's pairs."""
    import coal
    import pinocchio as pin

    text = re.sub(r"<collision>\s*<geometry>\s*<mesh[^>]*/>\s*</geometry>\s*</collision>", "",
                  FR3_URDF.read_text())
    model = pin.buildModelFromXML(text)
    geom = pin.buildGeomFromUrdfString(model, text, pin.COLLISION)
    for o in geom.geometryObjects:
        if isinstance(o.geometry, coal.Cylinder):
            o.geometry = coal.Capsule(o.geometry.radius, 2 * o.geometry.halfLength)
    index = {o.name: i for i, o in enumerate(geom.geometryObjects)}
    pin_name = lambda n: "{}_{}".format(*n.rsplit("/", 1))  # noqa: E731  (FR3's geoms are unnamed)
    for a, b in rc.pairs:
        geom.addCollisionPair(pin.CollisionPair(index[pin_name(a)], index[pin_name(b)]))
    data, gdata = model.createData(), pin.GeometryData(geom)

    def loop(Q) -> float:
        t0 = time.perf_counter()
        for q in Q:
            pin.computeDistances(model, data, geom, gdata, q)
        return (time.perf_counter() - t0) / len(Q)

    return loop


def _mujoco():
    """(per-row seconds function) for MuJoCo's mj_kinematics + mj_collision on the FR3."""
    import mujoco

    text = re.sub(r"<collision>\s*<geometry>\s*<mesh[^>]*/>\s*</geometry>\s*</collision>", "",
                  FR3_URDF.read_text())
    text = re.sub(r"<visual>.*?</visual>", "", text, flags=re.S).replace(
        '<robot name="fr3">', '<robot name="fr3"><mujoco><compiler fusestatic="false"/></mujoco>')
    m = mujoco.MjModel.from_xml_string(text)
    d = mujoco.MjData(m)

    def loop(Q) -> float:
        t0 = time.perf_counter()
        for q in Q:
            d.qpos[:] = q
            mujoco.mj_kinematics(m, d)
            mujoco.mj_collision(m, d)
        return (time.perf_counter() - t0) / len(Q)

    return loop


def run(args) -> list[dict]:
    quick = getattr(args, "quick", False)
    device = getattr(args, "device", "cpu")
    min_time, repeats = QUICK if quick else FULL
    batches = getattr(args, "batch", None) or ([1000, 10_000] if quick else [1000, 100_000])
    rows = []
    chain64, rc64 = _robot(torch.float64, "cpu")
    try:
        loop = _pin_coal(rc64)
    except ImportError:
        loop = None
    n = getattr(args, "peer_rows", None) or (500 if quick else 2000)
    Q = chain64.random_configuration((n,), generator=torch.Generator().manual_seed(1)).numpy()
    peer_times = [loop(Q) for _ in range(3)] if loop is not None else []  # before and after ours: noise
    try:
        mj = _mujoco()
    except ImportError:
        mj = None
    mj_times = [mj(Q) for _ in range(3)] if mj is not None else []
    for dtype in (torch.float32, torch.float64):
        chain, rc = _robot(dtype, device)
        for B in batches:
            q = chain.random_configuration((B,), generator=torch.Generator(device=device).manual_seed(0))
            with torch.no_grad():
                t = timeit(lambda rc=rc, q=q: rc.self_distances(q), min_time, repeats, device)
            rows.append({"benchmark": "collision", "impl": "diffkin", "batch": B, "dtype": str(dtype)[6:],
                         "device": device, "pairs": len(rc.pairs), "seconds": t, "us_per_row": 1e6 * t / B})
            if dtype == torch.float32 and B == min(batches):
                qg = q.clone().requires_grad_(True)
                t = timeit(lambda rc=rc, qg=qg: torch.autograd.grad(rc.min_distance(qg).sum(), qg), min_time,
                           repeats, device)
                rows.append({"benchmark": "collision", "impl": "diffkin +grad", "batch": B,
                             "dtype": "float32", "device": device, "pairs": len(rc.pairs), "seconds": t,
                             "us_per_row": 1e6 * t / B})
    peer = None
    if loop is not None:
        peer_times += [loop(Q) for _ in range(3)]
        peer = statistics.median(peer_times)
        rows.append({"benchmark": "collision", "impl": "pinocchio+coal (looped)", "batch": n,
                     "dtype": "float64", "device": "cpu", "pairs": len(rc64.pairs), "seconds": peer * n,
                     "us_per_row": 1e6 * peer, "us_per_row_min": 1e6 * min(peer_times),
                     "us_per_row_max": 1e6 * max(peer_times)})
    if mj is not None:
        mj_times += [mj(Q) for _ in range(3)]
        t = statistics.median(mj_times)
        rows.append({"benchmark": "collision", "impl": "mujoco mj_collision (looped, contacts only)",
                     "batch": n, "dtype": "float64", "device": "cpu", "pairs": len(rc64.pairs) + 9,
                     "seconds": t * n, "us_per_row": 1e6 * t, "us_per_row_min": 1e6 * min(mj_times),
                     "us_per_row_max": 1e6 * max(mj_times)})
    for r in rows:
        if peer is not None:
            r["speedup_vs_pin_coal"] = peer / (r["us_per_row"] * 1e-6)
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--batch", type=int, nargs="*", default=None)
    p.add_argument("--peer-rows", type=int, default=None)
    p.add_argument("--device", default="cpu")
    return cli(p, run, "FR3 self-distances (per row; the machine is shared: compare ratios)", argv)


if __name__ == "__main__":
    raise SystemExit(main())

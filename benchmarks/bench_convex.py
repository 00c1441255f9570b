"""Convex-mesh signed distances: the Panda's convex model beside its capsule model and coal, one thread.

    python -m benchmarks.bench_convex [--batch 64] [--pairs 2000]

Rows (float64, ``torch.set_num_threads(1)``: coal is single-threaded; medians of :func:`benchmarks.common.
timeit`):

* ``panda distances``: ``self_distances(q)`` and ``world_distances(q, world)`` of VAMP's Panda
  (``RobotCollision.from_urdf(panda.urdf)``, ``geometry="convex"`` and the default capsules) at ``--batch``
  random configurations in MotionBenchMaker's table_pick problem 41 (21 self pairs for the convex model,
  11 geoms x the scene's objects), per configuration; coal: Pinocchio's placements and ``coal.distance``
  (signed) between its hulls of the same meshes and the scene's boxes and cylinders, looped in Python.
* ``panda clear``: the collision decision (``_clear``, every distance >= 0, through the broad phase) of the
  same configurations, per configuration (the capsule model's goes through the fused C pass).
* ``convex-convex``: ``--pairs`` random pairs of random hulls (of 24 random points each, most of them in
  contact: EPA) in one batched call, per pair; coal looped over the same pairs (hulls built beforehand).

The machine is shared: compare ratios from one run.
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np
import torch

from benchmarks.common import timeit

F64 = torch.float64


def _panda(geometry):
    from benchmarks import motion_problems as mp
    from diffkin import models
    from diffkin.collision import RobotCollision

    chain = models.from_urdf(mp.PANDA_URDF, "panda_hand", dtype=F64)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return RobotCollision.from_urdf(mp.PANDA_URDF, chain, mp.PANDA_SRDF, geometry=geometry)


def _coal_panda(q, problem, rc):
    """Seconds per configuration of Pinocchio + coal on the same pairs."""
    import coal
    import pinocchio as pin

    from benchmarks import motion_problems as mp

    model = pin.buildModelFromUrdf(str(mp.PANDA_URDF))
    gmodel = pin.buildGeomFromUrdf(model, str(mp.PANDA_URDF), pin.COLLISION, package_dirs=[str(mp.DATA)])
    data, gdata = model.createData(), pin.GeometryData(gmodel)
    hulls = {}
    for k, go in enumerate(gmodel.geometryObjects):
        go.geometry.buildConvexHull(True, "Qt")
        hulls[model.frames[go.parentFrame].name] = (go.geometry.convex, k)
    link = {g.name: g.link for g in rc.geoms}
    pairs = [(hulls[link[a]], hulls[link[b]]) for a, b in rc.pairs]

    def tf(R, p):
        T = coal.Transform3s()
        T.setRotation(np.asarray(R, dtype=float))
        T.setTranslation(np.asarray(p, dtype=float))
        return T

    shapes = [(coal.Box(*o.dimensions) if o.kind == "box" else coal.Cylinder(*o.dimensions[::-1]),
               tf(o.pose[:3, :3].numpy(), o.pose[:3, 3].numpy())) for o in problem.scene.objects]
    req = coal.DistanceRequest()
    req.enable_signed_distance = True
    qs = q.numpy()
    t0 = time.perf_counter()
    for qk in qs:
        pin.updateGeometryPlacements(model, data, gmodel, gdata, qk)
        for (g1, i), (g2, j) in pairs:
            coal.distance(g1, gdata.oMg[i], g2, gdata.oMg[j], req, coal.DistanceResult())
        for g1, i in hulls.values():
            for g2, T in shapes:
                coal.distance(g1, gdata.oMg[i], g2, T, req, coal.DistanceResult())
    return (time.perf_counter() - t0) / len(qs)


def main(argv=None) -> None:
    from benchmarks import motion_problems as mp
    from diffkin.collision import convex as CV

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--pairs", type=int, default=2000)
    a = p.parse_args(argv)
    torch.set_num_threads(1)
    problem = mp.load_problems(families={"table_pick"}, indices={41})[0]
    world = problem.scene.to_world(dtype=F64)
    convex, capsules = _panda("convex"), _panda("capsules")
    chain = convex.chain
    lo, hi = chain.q_limits.T
    q = lo + (hi - lo) * torch.rand(a.batch, 7, dtype=F64, generator=torch.Generator().manual_seed(0))
    print(f"{'row':>16} {'convex us':>10} {'capsules us':>12} {'coal us':>9} {'convex/capsules':>16} "
          f"{'convex/coal':>12}")
    with torch.no_grad():
        both = lambda rc: lambda: (rc.self_distances(q), rc.world_distances(q, world))  # noqa: E731
        t_cv = timeit(both(convex), min_time=0.2, repeats=3) / a.batch
        t_cap = timeit(both(capsules), min_time=0.2, repeats=3) / a.batch
        t_coal = _coal_panda(q[: min(a.batch, 16)], problem, convex)
        print(f"{'panda distances':>16} {1e6 * t_cv:>10.1f} {1e6 * t_cap:>12.1f} {1e6 * t_coal:>9.1f} "
              f"{t_cv / t_cap:>16.1f} {t_cv / t_coal:>12.2f}")
        clear = lambda rc: lambda: rc._clear(q, world)  # noqa: E731
        c_cv = timeit(clear(convex), min_time=0.2, repeats=3) / a.batch
        c_cap = timeit(clear(capsules), min_time=0.2, repeats=3) / a.batch
        print(f"{'panda clear':>16} {1e6 * c_cv:>10.1f} {1e6 * c_cap:>12.1f} {'':>9} {c_cv / c_cap:>16.1f}")
        rng = np.random.default_rng(1)
        hulls = [rng.normal(size=(24, 3)) * rng.uniform(0.02, 0.12, 3) + rng.uniform(-0.15, 0.15, 3)
                 for _ in range(2 * a.pairs)]
        X = torch.tensor(np.stack(hulls[: a.pairs]), dtype=F64)
        V = torch.tensor(np.stack(hulls[a.pairs:]), dtype=F64)
        t_pair = timeit(lambda: CV.convex_convex(X, V), min_time=0.2, repeats=3) / a.pairs
    import coal

    def hull(P):
        pts = coal.StdVec_Vec3s()
        pts.extend(list(P))
        return coal.Convex.convexHull(pts, False, "")

    req, eye = coal.DistanceRequest(), coal.Transform3s()
    req.enable_signed_distance = True
    pairs = [(hull(x), hull(v)) for x, v in zip(hulls[: a.pairs], hulls[a.pairs:])]  # (not timed)
    t0 = time.perf_counter()
    for g1, g2 in pairs:
        coal.distance(g1, eye, g2, eye, req, coal.DistanceResult())
    t_pc = (time.perf_counter() - t0) / len(pairs)
    print(f"{'convex-convex':>16} {1e6 * t_pair:>10.1f} {'':>12} {1e6 * t_pc:>9.1f} {'':>16} "
          f"{t_pair / t_pc:>12.2f}")


if __name__ == "__main__":
    main()

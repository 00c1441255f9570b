"""Exact cylinder signed distances: diffkin's batched kernels beside coal looped over the same pairs.

    python -m benchmarks.bench_cylinders [--pairs 10000] [--coal-pairs 2000]

For each pair kind (sphere, capsule, box, cylinder against a cylinder) ``--pairs`` random pairs (centres in a
0.6 m cube, random axes and rotations, lengths 5-50 cm, radii 2-20 cm: about a quarter in contact) in
float64, one thread each (``torch.set_num_threads(1)``: coal is single-threaded). diffkin: one call of
:func:`diffkin.collision.sphere_cylinder` (closed form) /
``capsule_cylinder`` / ``box_cylinder`` / ``cylinder_cylinder`` (support-function search) on the whole
batch, under ``torch.no_grad()`` and with the backward pass (``+grad``). coal: ``coal.distance`` with
``enable_signed_distance`` (GJK, EPA in contact) looped in Python over ``--coal-pairs`` pairs (its cost is
linear in the pairs; scaled to ``--pairs``). Also the largest |diffkin − coal| over those pairs, apart and
in contact (coal's EPA failures, -DBL_MAX, left out; coal's sphere-cylinder depth with the centre inside the
cylinder is wrong, see tests/test_collision_cylinders.py). The machine is shared: compare ratios from one
run.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch


def main(argv=None) -> None:
    import coal

    from diffkin import collision as C
    from tests.test_collision_cylinders import _FN, _pairs  # the tests' pair generator and coal set-up

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--pairs", type=int, default=10000)
    p.add_argument("--coal-pairs", type=int, default=2000)
    a = p.parse_args(argv)
    del C, coal
    torch.set_num_threads(1)
    print(f"{'kind':>9} {'pairs':>6} {'diffkin s':>10} {'+grad s':>8} {'coal s (scaled)':>16} {'ratio':>6} "
          f"{'apart max|d-coal|':>18} {'contact':>9}")
    for kind in ("sphere", "capsule", "box", "cylinder"):
        t0 = time.perf_counter()
        args, ref = _pairs(kind, a.coal_pairs, seed=11)  # builds the coal objects and times coal's calls too
        t_build_and_coal = time.perf_counter() - t0
        big = [x.repeat(a.pairs // a.coal_pairs + 1, *([1] * (x.ndim - 1)))[: a.pairs] for x in args]
        _FN[kind](*(x[:8] for x in big))  # warm-up
        with torch.no_grad():
            t0 = time.perf_counter()
            d = _FN[kind](*big)
            t_ours = time.perf_counter() - t0
        xs = [x.clone().requires_grad_(True) for x in big]
        t0 = time.perf_counter()
        _FN[kind](*xs).sum().backward()
        t_grad = time.perf_counter() - t0
        coal_s = _coal_time(kind, a.coal_pairs) * a.pairs / a.coal_pairs
        err = np.abs(d[: a.coal_pairs].numpy() - ref)
        apart, contact = float(err[ref > 0].max()), float(err[(ref <= 0) & (ref > -1e3)].max())
        print(f"{kind:>9} {a.pairs:>6} {t_ours:>10.3f} {t_grad:>8.3f} {coal_s:>16.3f} "
              f"{t_ours / coal_s:>6.1f} {apart:>18.2e} {contact:>9.2e}   "
              f"(set-up incl. coal {t_build_and_coal:.2f} s)")


def _coal_time(kind: str, n: int) -> float:
    """Seconds of coal.distance alone over n pairs (objects built beforehand)."""
    import coal

    from tests.test_collision_cylinders import _axis_frame, _random_box, _random_cylinder, _tf

    rng = np.random.default_rng(11)
    objs = []
    for _ in range(n):
        a, b, r = _random_cylinder(rng)
        R, c, L = _axis_frame(a, b)
        g2, T2 = coal.Cylinder(r, L), _tf(R, c)
        if kind == "box":
            c1, R1, h = _random_box(rng)
            g1, T1 = coal.Box(*(2 * h)), _tf(R1, c1)
        elif kind == "sphere":
            g1, T1 = coal.Sphere(rng.uniform(0.0, 0.2)), _tf(np.eye(3), rng.uniform(-0.3, 0.3, 3))
        else:
            a1, b1, r1 = _random_cylinder(rng)
            R1, c1, L1 = _axis_frame(a1, b1)
            g1, T1 = (coal.Capsule if kind == "capsule" else coal.Cylinder)(r1, L1), _tf(R1, c1)
        objs.append((g1, T1, g2, T2))
    req = coal.DistanceRequest()
    req.enable_signed_distance = True
    t0 = time.perf_counter()
    for g1, T1, g2, T2 in objs:
        coal.distance(g1, T1, g2, T2, req, coal.DistanceResult())
    return time.perf_counter() - t0


if __name__ == "__main__":
    main()

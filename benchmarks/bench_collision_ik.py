"""Collision-free IK on the Franka FR3 (Panda's successor, Franka's coarse self-collision model: 30 spheres
and capsules, 288 checked pairs with link 1 - link 3 disabled as in MoveIt's SRDF) among a few obstacles.

    python -m benchmarks.bench_collision_ik [--targets 10000] [--world mixed|spheres] [--quick] [--json F]
        [--pyroki N] [--pyroki-recipes example,beam]

Targets: FK of uniformly random configurations whose every checked distance (self pairs and obstacles) is
>= 1 cm, so each target is reachable AND has a collision-free solution. Solved at 0.1 mm / 1 mrad by
``ik.solve(chain, T)`` and ``ik.solve(chain, T, collision=rc, world=world, margin=0)`` in the same run
(float32 chain, the same seed), each timed once on the whole batch (a solve of 10 000 targets takes
seconds: one call is the figure; ``--repeats`` for the median of more). ``success`` of the plain solve is
its pose success, ``collision_free`` the share of its solutions that are also clear (re-checked with the
exact distances); the collision solve's success includes the distances (its default on the CPU: rounds
of the whole C solve, each round's results checked in one batch and the colliding targets solved again
from other collision-free library poses, ik/_collision_native.py); "+ refinement":
``LMConfig(collision_refine_calls=1)`` (the scheduled torch loop, with a constrained Gauss-Newton
refinement of the colliding solutions first, ik/_collision.py).
``--world mixed``: two spheres and one box; ``spheres``: three spheres. The machine is shared: compare the
ratios of one run.

PyRoKi (JAX, CPU) runs beside it when it imports (``benchmarks/peers_pyroki.py``; it is not on PyPI, the
install recipe is in docs/collision.md): the first ``--pyroki N`` of the same targets (default 200, 20 with
``--quick``, 0 to skip; JAX on the CPU solves a few per second, so fewer than diffkin's), with the
recipes of ``--pyroki-recipes`` (``example``: its ``_solve_ik_with_collision`` snippet; ``beam``: its
benchmark's 64-seed beam with those collision costs), each jit-compiled and warmed up on one chunk
before the timed pass. PyRoKi solves a weighted least-squares problem with no tolerance, so its answers
are re-checked here (:func:`recheck`) with diffkin's float64 FK and exact distances (the real box, not
PyRoKi's capsule cover of it) at 0.1 mm / 1 mrad; the diffkin solutions of the same subset are re-checked
the same way (rows ``... (same N)``). Without pyroki one line says why and the rows are left out.
"""

from __future__ import annotations

import argparse
import statistics
import time
import warnings
from pathlib import Path

import torch

from benchmarks import peers_pyroki
from benchmarks.common import cli
from benchmarks.peers import SkipPeer
from diffkin import ik, models
from diffkin.collision import RobotCollision, World, box
from diffkin.ik.result import rotation_angle_between

__all__ = ["run", "main", "robot", "world", "targets", "recheck"]

FR3_URDF = Path(__file__).resolve().parents[1] / "tests" / "data" / "urdf" / "fr3.urdf"
SRDF = ('<robot name="fr3"><disable_collisions link1="fr3_link1_sc" link2="fr3_link3_sc" reason="Default"/>'
        '</robot>')


def robot(dtype=torch.float32, device="cpu"):
    chain = models.from_urdf(FR3_URDF, "fr3_link8", dtype=dtype, device=device).requires_grad_(False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the meshes are not shipped; the sc primitives are the model
        return chain, RobotCollision.from_urdf(FR3_URDF, chain, srdf=SRDF).requires_grad_(False)


def world(kind: str = "mixed", dtype=torch.float32, device="cpu") -> World:
    """Two spheres and a table-like box (``mixed``), or three spheres."""
    t = lambda x: torch.tensor(x, dtype=dtype, device=device)  # noqa: E731
    spheres = [[0.45, 0.25, 0.45, 0.10], [0.40, -0.30, 0.70, 0.08]]
    if kind == "spheres":
        return World(spheres=t(spheres + [[0.55, 0.0, 0.15, 0.08]]))
    return World(spheres=t(spheres), boxes=box(center=t([0.55, 0.0, 0.15]), half_extents=t([0.1, 0.3, 0.02]),
                                               dtype=dtype))


def targets(chain, rc, w, n: int, seed: int = 0, clear: float = 0.01):
    """(configurations (n, 7), poses (n, 4, 4)) of random configurations clear of collision by ``clear``."""
    g = torch.Generator(device=chain.device).manual_seed(seed)
    keep = []
    with torch.no_grad():
        while sum(len(k) for k in keep) < n:
            q = chain.random_configuration((4 * n,), generator=g)
            keep.append(q[rc.min_distance(q, w) >= clear])
        q = torch.cat(keep)[:n]
        return q, chain.forward_kinematics(q)


def _solve(chain, T, repeats: int, **kw):
    times, res = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        res = ik.solve(chain, T, seed=0, position_tolerance=1e-4, orientation_tolerance=1e-3, **kw)
        times.append(time.perf_counter() - t0)
    return res, times


def recheck(q, T, kind: str = "mixed") -> dict:
    """Pose success at 0.1 mm / 1 mrad and clearance of ``q (N, 7)`` for ``T (N, 4, 4)`` by float64 FK and
    exact distances (every checked self pair and obstacle >= 0), independent of the solver that gave q."""
    chain, rc = robot(torch.float64)
    q = torch.as_tensor(q, dtype=torch.float64)
    finite = torch.isfinite(q).all(-1)
    q = torch.where(finite[:, None], q, torch.zeros_like(q))
    T = torch.as_tensor(T, dtype=torch.float64)
    with torch.no_grad():
        Te = chain.forward_kinematics(q)
        free = finite & (rc.min_distance(q, world(kind, torch.float64)) >= 0.0)
    pe = torch.linalg.vector_norm(Te[:, :3, 3] - T[:, :3, 3], dim=-1)
    oe = rotation_angle_between(Te[:, :3, :3], T[:, :3, :3])
    ok = finite & (pe <= 1e-4) & (oe <= 1e-3) & chain.within_limits(q, tol=1e-6)
    coarse = finite & (pe <= 5e-3) & (oe <= 0.05)  # cuRobo's and PyRoKi's benchmark tolerance
    share = lambda m: float(m.double().mean())  # noqa: E731
    return {"success": share(ok), "collision_free": share(ok & free), "clear_any_pose": share(free),
            "success_5mm_50mrad": share(coarse), "position_error_median_m": float(pe.median())}


def _pyroki_rows(args, T, res_plain, res_coll, kind: str) -> list[dict]:
    """PyRoKi's recipes on the first ``--pyroki`` targets, and diffkin's answers on them, re-checked alike."""
    if getattr(args, "pyroki", None) == 0:
        return []
    m = min(len(T), getattr(args, "pyroki", None) or (20 if getattr(args, "quick", False) else 200))
    recipes = getattr(args, "pyroki_recipes", None) or "example"
    Tm = T[:m].double().numpy()
    rows = [{"impl": f"{name} (same {m})", "world": kind, "targets": m, **recheck(res.q[:m], Tm, kind)}
            for name, res in (("ik.solve", res_plain), ("ik.solve collision", res_coll))]
    for recipe in recipes.split(","):
        try:
            q, seconds = peers_pyroki.solve(Tm, kind, recipe)
        except SkipPeer as e:
            print(f"[bench_collision_ik] PyRoKi skipped: {e}")
            return []
        rows.append({"impl": f"PyRoKi {recipe} (JAX CPU)", "world": kind, "targets": m,
                     **recheck(q, Tm, kind), "seconds": seconds, "solves_per_s": m / seconds})
    return rows


def run(args) -> list[dict]:
    quick = getattr(args, "quick", False)
    n = getattr(args, "targets", None) or (200 if quick else 10_000)
    repeats = getattr(args, "repeats", None) or 1
    kind = getattr(args, "world", "mixed")
    chain, rc = robot()
    w = world(kind)
    _, T = targets(chain, rc, w, n)
    ik.solve(chain, T[:16], seed=0, collision=rc, world=w)  # warm-up (the C pass compiles once)
    rows, results = [], []
    coll = {"collision": rc, "world": w}
    refine = ik.LMConfig(collision_refine_calls=1)
    for name, kw in (("ik.solve", {}), ("ik.solve collision", coll),
                     ("ik.solve collision + refinement", {**coll, "config": refine})):
        res, times = _solve(chain, T, repeats, **kw)
        results.append(res)
        with torch.no_grad():
            free = rc.min_distance(res.q, w) >= 0.0
        t = statistics.median(times)
        rows.append({"impl": name, "world": kind, "targets": n, "success": float(res.success.float().mean()),
                     "collision_free": float((res.success & free).float().mean()), "seconds": t,
                     "solves_per_s": n / t, "seeds_mean": float(res.seeds_tried.float().mean())})
    for r in rows[1:]:
        r["speed_ratio"] = r["solves_per_s"] / rows[0]["solves_per_s"]
    return rows + _pyroki_rows(args, T, results[0], results[1], kind)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--targets", type=int, default=None)
    p.add_argument("--repeats", type=int, default=None)
    p.add_argument("--world", choices=("mixed", "spheres"), default="mixed")
    p.add_argument("--pyroki", type=int, default=None, help="targets for the PyRoKi peer (0: skip it)")
    p.add_argument("--pyroki-recipes", default="example", help="comma-separated: example, beam")
    return cli(p, run, "FR3 collision-free IK, 0.1 mm / 1 mrad (one run; the machine is shared)", argv)


if __name__ == "__main__":
    raise SystemExit(main())

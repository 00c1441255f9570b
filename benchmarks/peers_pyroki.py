"""PyRoKi (JAX) as an optional peer of the collision-free IK benchmark (``bench_collision_ik``), on the CPU.

PyRoKi is not on PyPI, and ``pip`` here reaches PyPI only; it installs from its repository (recipe in
docs/collision.md, "PyRoKi beside it"): ``jax[cpu]==0.6.2 jaxlie jax_dataclasses jaxtyping loguru termcolor
tqdm`` from PyPI, then ``pip install --no-deps`` of the sources of ``brentyi/jaxls`` @ e19f325 (PyPI's
``jaxls`` is an unrelated 5 kB package) and ``chungmin99/pyroki`` @ 70b30a5. Without it every entry point
raises :class:`benchmarks.peers.SkipPeer` with the reason.

The problem is the benchmark's: the FR3 URDF of tests/data (``fr3_link8``), its targets and its obstacles.
PyRoKi models the robot with **its own** collision model, ``pyroki.collision.RobotCollision.from_urdf``:
one capsule per link, the minimum bounding cylinder of the link's collision shapes (Franka's spheres and
cylinders on the ``*_sc`` links; the mesh collisions are dropped, their files are not shipped) made a
capsule of that radius whose *segment* is the cylinder's height, so each capsule reaches one radius beyond
Franka's geometry at both ends (coarser than diffkin's 30 exact geoms, and conservative). Links without
geometry become points at their origins. Checked self pairs: ``*_sc`` links two
or more joints apart, as diffkin checks, less :data:`NEVER` (link 1 - link 3 as in the benchmark's SRDF,
and 3 - 5 and 5 - 7, which PyRoKi's capsules make overlap in nearly every configuration); every other pair
goes to ``user_ignore_pairs``. Obstacles: spheres as ``pyroki.collision.Sphere``; PyRoKi has no box, so
the box is covered by :data:`BOX_CAPSULES` capsules along its long axis, centres spread across its width,
radius 3.2 cm for its 2 cm half-thickness (they contain it; rounded ends reach 3.2 cm beyond it).
Answers are re-checked by the caller with diffkin's float64 FK and exact
distances to the real box, never by PyRoKi.

Recipes (``RECIPES``), both PyRoKi's own, batched with ``jax.vmap`` over targets and ``jax.jit``:

* ``example``: ``examples/pyroki_snippets/_solve_ik_with_collision.py`` verbatim (pose 5 / 1, limits 100,
  rest 0.01, self-collision margin 2 cm weight 5, world margin 5 cm weight 10; one LM solve from the middle
  of the limits, jaxls' default termination, dense Cholesky);
* ``beam``: the seeding of PyRoKi's ``benchmark/ik_benchmark.py`` (its cuRobo comparison: 64 quasi-random
  seeds x 6 LM steps, the best 4 continued for 10 more, the lowest cost kept; pose 10 / 5, limits 50) with
  the example's two collision costs added.
"""

from __future__ import annotations

import io
import re
import time
from functools import lru_cache
from pathlib import Path

import numpy as np

from benchmarks.peers import SkipPeer

__all__ = ["RECIPES", "BOX_CAPSULES", "available", "problem", "solve"]

FR3_URDF = Path(__file__).resolve().parents[1] / "tests" / "data" / "urdf" / "fr3.urdf"
END_LINK = "fr3_link8"
RECIPES = ("example", "beam")
#: capsules covering the benchmark's box (centre, half extents (0.1, 0.3, 0.02)), one per x offset
BOX_CAPSULES = 5
#: sc link pairs not checked: 1-3 (the benchmark's SRDF); 3-5 and 5-7, whose PyRoKi capsules overlap in
#: 97.7 % and 100 % of 2 000 uniformly random configurations (MoveIt's "Always" rule for PyRoKi's model)
NEVER = ({1, 3}, {3, 5}, {5, 7})


def available() -> str | None:
    """None when PyRoKi and its JAX stack import, else the reason (the ImportError's text)."""
    try:
        import jax  # noqa: F401
        import jaxlie  # noqa: F401
        import jaxls  # noqa: F401
        import pyroki  # noqa: F401
        import yourdfpy  # noqa: F401
    except Exception as e:  # noqa: BLE001 - any failure to import means no peer; say which
        return f"pyroki does not import ({type(e).__name__}: {e}); install recipe in docs/collision.md"
    return None


def _fr3_primitives_urdf() -> str:
    """The FR3 URDF without visuals and mesh collisions (files not shipped): Franka's sc primitives stay."""
    src = FR3_URDF.read_text()
    src = re.sub(r"<visual>.*?</visual>", "", src, flags=re.S)
    return re.sub(r"<collision>(?:(?!</collision>).)*<mesh[^>]*/>(?:(?!</collision>).)*</collision>", "", src,
                  flags=re.S)


def _ignore_pairs(names: tuple[str, ...]) -> tuple[tuple[str, str], ...]:
    """Every link pair but the ``*_sc`` links two or more joints apart, less the :data:`NEVER` pairs."""
    sc = {n: int(n[len("fr3_link"):-3]) for n in names if n.endswith("_sc")}
    ignore = []
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            if a not in sc or b not in sc or abs(sc[a] - sc[b]) < 2 or {sc[a], sc[b]} in NEVER:
                ignore.append((a, b))
    return tuple(ignore)


def _world_geoms(spheres: np.ndarray, boxes: list[tuple[np.ndarray, np.ndarray]]):
    """PyRoKi geometry of the obstacles: a Sphere stack, and capsules covering each axis-aligned box."""
    import jax.numpy as jnp
    from pyroki.collision import Capsule, Sphere

    geoms = [Sphere.from_center_and_radius(jnp.asarray(spheres[:, :3]), jnp.asarray(spheres[:, 3]))]
    for center, half in boxes:
        long_ax = int(np.argmax(half))
        short = [a for a in range(3) if a != long_ax]
        wide, thin = sorted(short, key=lambda a: -half[a])
        s = 2 * half[wide] / (BOX_CAPSULES - 1)  # centres on the box's edge and inside, spacing s
        r = float(np.hypot(s / 2, half[thin]))  # the circles then cover the cross-section
        pos = np.repeat(center[None], BOX_CAPSULES, axis=0)
        pos[:, wide] += np.linspace(-half[wide], half[wide], BOX_CAPSULES)
        z = np.zeros(3)
        z[long_ax] = 1.0  # PyRoKi capsules run along their local z: rotate z onto the long axis
        wxyz = _quat_z_to(z)
        geoms.append(Capsule.from_radius_height(radius=jnp.full((BOX_CAPSULES,), r),
                                                height=jnp.full((BOX_CAPSULES,), 2 * half[long_ax]),
                                                position=jnp.asarray(pos), wxyz=jnp.asarray(wxyz)))
    return geoms


def _quat_z_to(v: np.ndarray) -> np.ndarray:
    """wxyz of the shortest rotation taking +z onto the unit vector v (v != -z)."""
    c = np.cross([0.0, 0.0, 1.0], v)
    q = np.array([1.0 + v[2], *c])
    return q / np.linalg.norm(q)


@lru_cache(maxsize=4)
def problem(kind: str = "mixed"):
    """(robot, robot collision, world geoms, end link index) of PyRoKi for the benchmark's world ``kind``."""
    reason = available()
    if reason:
        raise SkipPeer(reason)
    import jax.numpy as jnp
    import pyroki as pk
    import yourdfpy
    from loguru import logger

    logger.disable("pyroki")  # their INFO lines (joint sorting, pair count, vectorised groups) would flood
    logger.disable("jaxls")  # the benchmark output
    urdf = yourdfpy.URDF.load(io.StringIO(_fr3_primitives_urdf()), load_meshes=False,
                              load_collision_meshes=False)
    robot = pk.Robot.from_urdf(urdf)
    rc = pk.collision.RobotCollision.from_urdf(urdf, user_ignore_pairs=_ignore_pairs(robot.links.names))
    spheres = np.array([[0.45, 0.25, 0.45, 0.10], [0.40, -0.30, 0.70, 0.08]])
    if kind == "spheres":
        spheres, boxes = np.vstack([spheres, [0.55, 0.0, 0.15, 0.08]]), []
    else:
        boxes = [(np.array([0.55, 0.0, 0.15]), np.array([0.1, 0.3, 0.02]))]
    return robot, rc, tuple(_world_geoms(spheres, boxes)), jnp.array(robot.links.names.index(END_LINK))


def _costs(pk, robot, rc, world, joint_var, target, link, pose_w, limit_w, rest_w):
    import jax.numpy as jnp

    costs = [pk.costs.pose_cost(robot, joint_var, target_pose=target, target_link_index=link,
                                pos_weight=pose_w[0], ori_weight=pose_w[1]),
             pk.costs.limit_cost(robot, joint_var=joint_var, weight=limit_w),
             pk.costs.self_collision_cost(robot, robot_coll=rc, joint_var=joint_var, margin=0.02, weight=5.0)]
    if rest_w:
        costs.append(pk.costs.rest_cost(joint_var, rest_pose=jnp.array(joint_var.default_factory()),
                                        weight=rest_w))
    return costs + [pk.costs.world_collision_cost(robot, rc, joint_var, g, 0.05, 10.0) for g in world]


def _example_fn(robot, rc, world, link):
    """PyRoKi's _solve_ik_with_collision for one target (wxyz_xyz (7,)) -> q (7,)."""
    import jaxlie
    import jaxls
    import pyroki as pk

    def one(wxyz_xyz):
        joint_var = robot.joint_var_cls(0)
        costs = _costs(pk, robot, rc, world, joint_var, jaxlie.SE3(wxyz_xyz), link, (5.0, 1.0), 100.0, 0.01)
        sol = jaxls.LeastSquaresProblem(costs, [joint_var]).analyze().solve(
            verbose=False, linear_solver="dense_cholesky")
        return sol[joint_var]
    return one


def _roberts(num: int, dim: int):
    """The quasi-random seeds of PyRoKi's ik_benchmark.py (Roberts' sequence in [0, 1)^dim)."""
    import jax.numpy as jnp

    root = 1.0
    for _ in range(10_000):  # Newton for x^(dim+1) = x + 1, as there
        root -= (root ** (dim + 1) - root - 1) / ((dim + 1) * root ** dim - 1)
    basis = 1 - (1 / root ** (1 + jnp.arange(dim)))
    return jnp.modf(jnp.arange(num)[:, None] * basis[None, :])[0]


def _beam_fn(robot, rc, world, link, seeds: int = 64, keep: int = 4, steps: tuple[int, int] = (6, 10)):
    """PyRoKi ik_benchmark.py's beam (64 seeds, best 4 continued) with the example's collision costs."""
    import jax
    import jax.numpy as jnp
    import jaxlie
    import jaxls
    import pyroki as pk

    lo, hi = robot.joints.lower_limits, robot.joints.upper_limits
    q0 = lo + _roberts(seeds, robot.joints.num_actuated_joints) * (hi - lo)

    def solve_from(target, q_init, lam, iters):
        joint_var = robot.joint_var_cls(0)
        costs = _costs(pk, robot, rc, world, joint_var, target, link, (10.0, 5.0), 50.0, 0.0)
        sol, summary = jaxls.LeastSquaresProblem(costs, [joint_var]).analyze().solve(
            initial_vals=jaxls.VarValues.make([joint_var.with_value(q_init)]), verbose=False,
            linear_solver="dense_cholesky",
            termination=jaxls.TerminationConfig(max_iterations=iters, early_termination=False),
            trust_region=jaxls.TrustRegionConfig(lambda_initial=lam), return_summary=True)
        return sol[joint_var], summary

    def one(wxyz_xyz):
        target = jaxlie.SE3(wxyz_xyz)
        many = jax.vmap(solve_from, in_axes=(None, 0, 0, None))
        q1, s1 = many(target, q0, jnp.full((seeds,), 10.0), steps[0])
        best = jnp.argsort(s1.cost_history[jnp.arange(seeds), -1])[:keep]
        q2, s2 = many(target, q1[best], s1.lambda_history[jnp.arange(seeds), -1][best], steps[1])
        return q2[jnp.argmin(s2.cost_history[jnp.arange(keep), s2.iterations])]
    return one


def solve(T: np.ndarray, kind: str = "mixed", recipe: str = "example",
          chunk: int = 500) -> tuple[np.ndarray, float]:
    """PyRoKi's collision IK of targets ``T (N, 4, 4)`` (base frame, metres) -> (q (N, 7) float64, seconds).

    ``jax.jit(jax.vmap(recipe))`` over chunks of ``chunk`` targets (the last one padded), compiled and run
    once on the first chunk before timing; seconds are the wall time of all chunks, each ended by
    ``block_until_ready``.
    """
    if recipe not in RECIPES:
        raise ValueError(f"recipe must be one of {RECIPES}, got {recipe!r}")
    robot, rc, world, link = problem(kind)
    import jax
    import jax.numpy as jnp
    import jaxlie

    make = _example_fn if recipe == "example" else _beam_fn
    fn = jax.jit(jax.vmap(make(robot, rc, world, link)))
    n = len(T)
    chunk = min(chunk, n)
    pad = -n % chunk
    T = np.concatenate([T, np.repeat(T[-1:], pad, axis=0)]) if pad else T
    wxyz_xyz = jaxlie.SE3.from_matrix(jnp.asarray(T, dtype=jnp.float32)).wxyz_xyz
    jax.block_until_ready(fn(wxyz_xyz[:chunk]))  # compile + warm-up, not timed
    out, t0 = [], time.perf_counter()
    for i in range(0, len(T), chunk):
        out.append(jax.block_until_ready(fn(wxyz_xyz[i:i + chunk])))
    seconds = time.perf_counter() - t0
    return np.asarray(jnp.concatenate(out), dtype=np.float64)[:n], seconds

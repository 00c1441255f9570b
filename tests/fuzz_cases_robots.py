"""Fuzz cases of the robot-level API: chains, models, redundancy (the pinv family), ik
(see ``tests/fuzzing.py`` for the format).

Chain methods are fuzzed through ``Case.chain`` (the chain of the call's dtype, passed first), so the
``mixed`` mutation converts an argument away from the chain's dtype. The IK solver cases also check that
the success flags are honest: a target flagged successful is within the tolerances by an independent float64
FK of the returned joints (an AssertionError, classified ``crash``, otherwise).
"""

from __future__ import annotations

import functools
from pathlib import Path

import torch

from diffkin import ik, models, redundancy
from diffkin.chain import DHChain, KinematicChain
from diffkin.sampling import configuration_from_uniform
from tests.fuzzing import Arg, Case, transform, uniform

DATA = Path(__file__).parent / "data" / "urdf"
ALLEGRO_TIPS = ["link_3.0_tip", "link_7.0_tip", "link_11.0_tip", "link_15.0_tip"]


# ------------------------------------------------------------------------------------------ chains
@functools.cache
def panda(dtype: torch.dtype) -> DHChain:
    return models.load("panda", dtype=dtype)


@functools.cache
def ur5(dtype: torch.dtype) -> DHChain:
    return models.load("ur5", dtype=dtype)


@functools.cache
def floating(dtype: torch.dtype):
    """A chain with ball and free joints (q (..., 22), v (..., 19)): every MuJoCo joint type."""
    return models.from_mjcf(Path(__file__).parent / "data" / "mjcf_extra" / "joint_kinds.xml",
                            ["palm", "foot", "box"], dtype=dtype)


@functools.cache
def hand(dtype: torch.dtype):
    return models.from_urdf(DATA / "allegro_right_hand.urdf", ALLEGRO_TIPS, dtype=dtype)


# ----------------------------------------------------------------------------------- value builders
def joints(chain_of, *, trailing: tuple[int, ...] = ()):
    """``make`` for joint vectors within the limits of ``chain_of(dtype)``: (*batch, *trailing, n)."""

    def make(gen, batch, dtype):
        return chain_of(dtype).random_configuration((*batch, *trailing), generator=gen)

    return make


def poses(chain_of, *, steps: int | None = None, positions: bool = False):
    """``make`` for reachable end poses (FK of joints within the limits); with ``steps`` a short path
    ``(*batch, steps, 4, 4)`` (joints moving 0.02 rad a sample); ``positions``: their positions."""

    def make(gen, batch, dtype):
        chain = chain_of(dtype)
        q = chain.random_configuration(batch, generator=gen)
        if steps is not None:
            ramp = 0.02 * torch.arange(steps, dtype=dtype)[:, None]
            q = chain.clamp_to_limits(q[..., None, :] + ramp)
        with torch.no_grad():
            T = chain.forward_kinematics(q)
        return T[..., :3, 3].contiguous() if positions else T

    return make


def matrix(m: int, n: int, rank: int | None = None):
    """``make`` for random (..., m, n) matrices, of the given rank (a product of two random factors)."""

    def make(gen, batch, dtype):
        if rank is None:
            return uniform(m, n)(gen, batch, dtype)
        A = torch.randn(*batch, m, rank, generator=gen, dtype=torch.float64)
        return (A @ torch.randn(*batch, rank, n, generator=gen, dtype=torch.float64)).to(dtype)

    return make


def positive(*trailing: int, low: float = 0.5, high: float = 2.0):
    return uniform(*trailing, low=low, high=high)


def limits(which: int):
    """``make`` for the Panda's lower (0) or upper (1) joint limits, (7,)."""

    def make(gen, batch, dtype):
        return panda(dtype).q_limits[:, which].clone()

    return make


def dh_column(col: int):
    """``make`` for a column of the Panda's DH table (7,), perturbed a little."""

    def make(gen, batch, dtype):
        base = panda(dtype).dh_table()[:, col]
        return base + 0.01 * torch.rand(7, generator=gen, dtype=dtype)

    return make


# ------------------------------------------------------------------------------------- honesty check
def honest(chain, T_target, res, position_only: bool, ptol: float, otol: float):
    """Raise AssertionError when a target flagged successful is not within the tolerances by a float64 FK
    of the returned joints (slack: the rounding of the chain's dtype)."""
    c64 = chain.double() if chain.dtype == torch.float64 else _double(chain)
    with torch.no_grad():
        T = c64.forward_kinematics(res.q.detach().double())
        Td = T_target.double() if isinstance(T_target, torch.Tensor) else torch.as_tensor(T_target).double()
        p_d = Td if Td.shape[-1] == 3 and position_only else Td[..., :3, 3]
        pe = (p_d - T[..., :3, 3]).norm(dim=-1)
        slack = 50 * torch.finfo(chain.dtype).eps * (1.0 + p_d.abs().amax(-1))
        ok = pe <= ptol + slack
        if not position_only:
            R = T[..., :3, :3].mT @ Td[..., :3, :3]
            cos = ((R.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1, 1)
            ok &= torch.arccos(cos) <= otol + 1e-3 * float(torch.finfo(chain.dtype).eps) ** 0.5 + 1e-6
        if ok.ndim > res.success.ndim:  # K end links
            ok = ok.all(-1)
        if chain.q_limits is not None:
            ok &= chain.within_limits(res.q.detach(), tol=1e-6)
        bad = res.success & ~ok
        assert not bool(bad.any()), f"{int(bad.sum())} targets flagged successful outside the tolerances"
    return res


@functools.cache
def _double(chain):
    import copy

    return copy.deepcopy(chain).double()


def solve_honest(chain, T, **kw):
    kw = {"num_seeds": 4, "max_iterations": 6, "seed": 0, **kw}
    res = ik.solve(chain, T, **kw)
    return honest(chain, T, res, kw.get("position_only", False), kw.get("position_tolerance", 1e-4),
                  kw.get("orientation_tolerance", 1e-3))


def solve_seeded(chain, T, q0):
    res = ik.solve(chain, T, q0, num_seeds=2, max_iterations=6, seed=0)
    return honest(chain, T, res, False, 1e-4, 1e-3)


def optimize_honest(chain, T, q0):
    res = ik.optimize(chain, T, q0, optimizer="gauss_newton", max_iterations=4)
    return honest(chain, T, res, False, 1e-4, 1e-3)


@functools.cache
def fr3(dtype: torch.dtype):
    return models.from_urdf(DATA / "fr3.urdf", "fr3_link8", dtype=dtype)


@functools.cache
def fr3_collision(dtype: torch.dtype):
    """The FR3's collision model (link 1-3 off, as MoveIt's SRDF) and two obstacle spheres, in ``dtype``."""
    import warnings

    from diffkin.collision import RobotCollision, World

    srdf = '<robot><disable_collisions link1="fr3_link1_sc" link2="fr3_link3_sc" reason="Default"/></robot>'
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the FR3's meshes are not shipped
        rc = RobotCollision.from_urdf(DATA / "fr3.urdf", fr3(dtype), srdf=srdf).requires_grad_(False)
    return rc, World(spheres=torch.tensor([[0.45, 0.25, 0.45, 0.1], [0.4, -0.3, 0.7, 0.08]], dtype=dtype))


def solve_collision_honest(chain, T):
    """ik.solve(collision=, world=): flagged successes within the tolerances and clear of collision."""
    rc, world = fr3_collision(chain.dtype)
    res = solve_honest(chain, T, collision=rc, world=world, margin=0.002)
    with torch.no_grad():
        d = rc.min_distance(res.q, world)
    assert not bool((res.success & (d < 0.002)).any()), "a success in collision"
    return res


def optimize_collision_honest(chain, T, q0):
    rc, world = fr3_collision(chain.dtype)
    res = ik.optimize(chain, T, q0, optimizer="gauss_newton", max_iterations=4, collision=rc, world=world)
    with torch.no_grad():
        assert not bool((res.success & (rc.min_distance(res.q, world) < 0.0)).any()), "a success in collision"
    return honest(chain, T, res, False, 1e-4, 1e-3)


def _set_pose(chain, which: str, T):
    c = chain.copy()
    setattr(c, which, T)
    return getattr(c, which)


# --------------------------------------------------------------------------------------------- cases
Q = Arg(joints(panda), (7,))
CH = {"chain": panda, "follows_chain": True}

CASES: list[Case] = [
    # --- chain methods (KinematicChain / DHChain)
    Case("chain.forward_kinematics", lambda c, q: c.forward_kinematics(q), {"q": Q}, **CH,
         covers=KinematicChain.forward_kinematics),
    Case("chain.forward_kinematics[all_frames]", lambda c, q: c.forward_kinematics(q, all_frames=True),
         {"q": Q}, **CH, covers=KinematicChain.forward_kinematics),
    Case("chain.forward_kinematics[large batch]", lambda c, q: c.forward_kinematics(q), {"q": Q}, **CH,
         batch=(40,), covers=KinematicChain.forward_kinematics),
    Case("chain.forward_kinematics[urdf tree]", lambda c, q: c.forward_kinematics(q),
         {"q": Arg(joints(hand), (16,))}, chain=hand, follows_chain=True,
         covers=KinematicChain.forward_kinematics),
    Case("chain.forward_kinematics[mjcf floating]", lambda c, q: c.forward_kinematics(q),
         {"q": Arg(joints(floating), (22,))}, chain=floating, follows_chain=True,
         covers=KinematicChain.forward_kinematics),
    Case("chain.forward_kinematics_and_jacobian[mjcf floating]",
         lambda c, q: c.forward_kinematics_and_jacobian(q), {"q": Arg(joints(floating), (22,))},
         chain=floating, follows_chain=True, batch=(20,),
         covers=KinematicChain.forward_kinematics_and_jacobian),
    Case("chain.integrate", lambda c, q, v: c.integrate(q, v),
         {"q": Arg(joints(floating), (22,)), "v": Arg(uniform(19), (19,))}, chain=floating,
         follows_chain=True, covers=KinematicChain.integrate),
    Case("chain.difference", lambda c, q0, q1: c.difference(q0, q1),
         {"q0": Arg(joints(floating), (22,)), "q1": Arg(joints(floating), (22,))}, chain=floating,
         follows_chain=True, covers=KinematicChain.difference),
    Case("chain.forward", lambda c, q: c(q), {"q": Q}, **CH, covers=KinematicChain.forward),
    Case("chain.forward_kinematics_and_jacobian[point]",
         lambda c, q, point: c.forward_kinematics_and_jacobian(q, frame="ee", point=point),
         {"q": Q, "point": Arg(uniform(3), (3,))}, **CH,
         covers=KinematicChain.forward_kinematics_and_jacobian),
    Case("sampling.configuration_from_uniform[mjcf floating]", configuration_from_uniform,
         {"u": Arg(uniform(19, low=0, high=1), (19,))}, chain=floating, follows_chain=True),
    Case("sampling.configuration_from_uniform", configuration_from_uniform,
         {"u": Arg(uniform(7, low=0, high=1), (7,))}, **CH),
    Case("chain.joint_axes_origins", lambda c, q: c.joint_axes_origins(q), {"q": Q}, **CH,
         covers=KinematicChain.joint_axes_origins),
    Case("chain.geometric_jacobian", lambda c, q: c.geometric_jacobian(q), {"q": Q}, **CH,
         covers=KinematicChain.geometric_jacobian),
    Case("chain.analytical_jacobian", lambda c, q: c.analytical_jacobian(q, singular="ignore"), {"q": Q},
         **CH, covers=KinematicChain.analytical_jacobian),
    Case("chain.forward_kinematics_and_jacobian", lambda c, q: c.forward_kinematics_and_jacobian(q),
         {"q": Q}, **CH, covers=KinematicChain.forward_kinematics_and_jacobian),
    Case("chain.parameter_jacobian", lambda c, q: c.parameter_jacobian(q)[0], {"q": Q}, **CH, batch=(2,),
         covers=KinematicChain.parameter_jacobian),
    # batch_last takes qT (n, m): the case passes q (m, n) transposed; the Jacobian rows (n, 6, m) carry m
    Case("chain.batch_last", lambda c, q: c.batch_last(q.mT if isinstance(q, torch.Tensor) else q.T,
                                                       with_jacobian=True),
         {"q": Arg(joints(panda), (7,))}, **CH, out_batch=lambda r: r[0].movedim(-1, 0),
         covers=KinematicChain.batch_last),
    Case("chain.within_limits", lambda c, q: c.within_limits(q), {"q": Q}, **CH,
         covers=KinematicChain.within_limits),
    Case("chain.clamp_to_limits", lambda c, q: c.clamp_to_limits(q), {"q": Arg(uniform(7, low=-4, high=4),
                                                                                 (7,))},
         **CH, covers=KinematicChain.clamp_to_limits),
    Case("chain.check_q", lambda c, q: c.check_q(q), {"q": Q}, **CH, covers=KinematicChain.check_q),
    Case("chain.base", lambda c, T: _set_pose(c, "base", T), {"T": Arg(transform, (4, 4), batched=False)},
         **CH, out_batch=None),
    Case("chain.tool", lambda c, T: _set_pose(c, "tool", T), {"T": Arg(transform, (4, 4), batched=False)},
         **CH, out_batch=None),
    Case("chain.DHChain", lambda a, alpha, d, theta: DHChain(a, alpha, d, theta).dh_table(),
         {"a": Arg(dh_column(0), (7,), batched=False), "alpha": Arg(dh_column(1), (7,), batched=False),
          "d": Arg(dh_column(2), (7,), batched=False), "theta": Arg(dh_column(3), (7,), batched=False)},
         out_batch=None, covers=DHChain),
    # --- redundancy (the pinv family). J of any (m, n) is valid input (a changed trailing size is another
    # valid J), so J has no shape mutation; the shape rules are between J and the other arguments.
    Case("redundancy.pinv", redundancy.pinv, {"J": Arg(matrix(6, 7))}),
    Case("redundancy.pinv[tall]", redundancy.pinv, {"J": Arg(matrix(6, 4))}, covers=redundancy.pinv),
    Case("redundancy.pinv[singular]", redundancy.pinv, {"J": Arg(matrix(6, 7, rank=4))},
         covers=redundancy.pinv),
    Case("redundancy.damped_pinv", redundancy.damped_pinv,
         {"J": Arg(matrix(6, 7)), "damping": Arg(positive(low=0.01, high=0.1))}),
    Case("redundancy.damped_pinv[zero damping]", redundancy.damped_pinv,
         {"J": Arg(matrix(6, 7, rank=3)), "damping": Arg(lambda g, b, dt: torch.zeros(b, dtype=dt))},
         covers=redundancy.damped_pinv),
    Case("redundancy.damped_pinv[adaptive]", redundancy.damped_pinv,
         {"J": Arg(matrix(6, 7)), "damping": Arg(positive(low=0.01, high=0.1))},
         fixed={"threshold": 0.1}, covers=redundancy.damped_pinv),
    Case("redundancy.weighted_pinv", redundancy.weighted_pinv,
         {"J": Arg(matrix(6, 7)), "W": Arg(positive(7), (7,))}),
    # W (..., 7, 7) with a dimension dropped is (..., 7): the diagonal form, valid input (refused here only
    # because the rows of a diagonal matrix hold zeros, not by shape) -> no shape mutation for W
    Case("redundancy.weighted_pinv[matrix]", lambda J, W: redundancy.weighted_pinv(J, W, damping=0.01),
         {"J": Arg(matrix(3, 7, rank=2)),
          "W": Arg(lambda g, b, dt: torch.diag_embed(positive(7)(g, b, dt)), (7, 7))},
         skip=("shape:W",), covers=redundancy.weighted_pinv),
    Case("redundancy.nullspace_projector", redundancy.nullspace_projector, {"J": Arg(matrix(6, 7, rank=5))}),
    # --- ik
    Case("ik.dls_delta", ik.dls_delta, {"J": Arg(matrix(6, 7)), "err": Arg(uniform(6), (6,))},
         fixed={"damping": 0.05}),
    Case("ik.dls_delta[zero damping]", ik.dls_delta,
         {"J": Arg(matrix(6, 7, rank=3)), "err": Arg(uniform(6), (6,))},
         fixed={"damping": 0.0}, covers=ik.dls_delta),
    Case("ik.dls_step", lambda c, q, T: ik.dls_step(c, q, T), {"q": Q, "T_target": Arg(poses(panda), (4, 4))},
         **CH, covers=ik.dls_step),
    Case("ik.dls_step[position_only]", lambda c, q, p: ik.dls_step(c, q, p, position_only=True),
         {"q": Q, "p_target": Arg(poses(panda, positions=True), (3,))}, **CH, covers=ik.dls_step),
    Case("ik.solve", solve_honest, {"T_target": Arg(poses(panda), (4, 4))}, **CH, covers=ik.solve),
    Case("ik.solve[position_only]", lambda c, p: solve_honest(c, p, position_only=True),
         {"p_target": Arg(poses(panda, positions=True), (3,))}, **CH, covers=ik.solve),
    Case("ik.solve[q0]", solve_seeded, {"T_target": Arg(poses(panda), (4, 4)), "q0": Q}, **CH,
         covers=ik.solve),
    Case("ik.solve[tree]", lambda c, p: solve_honest(c, p, position_only=True, num_seeds=2),
         {"p_target": Arg(lambda g, b, dt: poses(hand, positions=True)(g, b, dt), (4, 3))},
         chain=hand, follows_chain=True, batch=(2,), covers=ik.solve),
    Case("ik.solve[collision]", solve_collision_honest, {"T_target": Arg(poses(fr3), (4, 4))}, chain=fr3,
         follows_chain=True, covers=ik.solve),
    Case("ik.optimize[collision]", optimize_collision_honest,
         {"T_target": Arg(poses(fr3), (4, 4)), "q0": Arg(joints(fr3), (7,))}, chain=fr3, follows_chain=True,
         covers=ik.optimize),
    Case("ik.optimize", optimize_honest, {"T_target": Arg(poses(panda), (4, 4)), "q0": Q}, **CH,
         covers=ik.optimize),
    Case("ik.clik", lambda c, q0, xd: ik.clik(c, (xd,), q0, 0.01, 3), {"q0": Q, "x_d": Arg(
        poses(panda, steps=3), (3, 4, 4))}, **CH, out_batch=lambda r: r.q, covers=ik.clik),
    # S = 4 samples, not 3 like the batch: an (S, 6) derivative without batch dims is valid input
    Case("ik.clik[second_order]", lambda c, q0, xd, vd: ik.clik(c, (xd, vd), q0, 0.01, 3,
                                                                 algorithm="second_order"),
         {"q0": Q, "x_d": Arg(poses(panda, steps=4), (4, 4, 4)), "xdot_d": Arg(uniform(4, 6), (4, 6))},
         **CH, out_batch=lambda r: r.q, covers=ik.clik),
    # a position target tensor as the first argument: the old-order detection must leave it there
    Case("ik.clik[position tensor]", lambda c, pd, q0: ik.clik(c, pd, q0, 0.01, 3, orientation=None),
         {"p_d": Arg(poses(panda, steps=3, positions=True), (3, 3)), "q0": Q}, **CH,
         out_batch=lambda r: r.q, covers=ik.clik),
    Case("ik.closed_form", lambda c, T: ik.closed_form(c, T), {"T_target": Arg(poses(ur5), (4, 4))},
         chain=ur5, follows_chain=True, covers=ik.closed_form),
    Case("ik.joint_limit_objective", ik.joint_limit_objective,
         {"q": Q, "lower": Arg(limits(0), (7,), batched=False),
          "upper": Arg(limits(1), (7,), batched=False)}),
    Case("ik.joint_trajectory_from_poses", lambda c, T, q0: ik.joint_trajectory_from_poses(c, T, q0),
         {"T_traj": Arg(poses(panda, steps=3), (3, 4, 4)), "q0": Q}, **CH,
         covers=ik.joint_trajectory_from_poses),
    Case("ik.joint_trajectory_from_poses[solve]",
         lambda c, T, q0: ik.joint_trajectory_from_poses(c, T, q0, method="solve", num_seeds=2, seed=0,
                                                          max_iterations=6),
         {"T_traj": Arg(poses(panda, steps=2), (2, 4, 4)), "q0": Q}, **CH,
         covers=ik.joint_trajectory_from_poses),
    Case("ik.velocity_step", lambda c, q, tw: ik.velocity_step(c, q, tw, 0.05, velocity_limit=1.0),
         {"q": Q, "twist": Arg(uniform(6), (6,))}, **CH, covers=ik.velocity_step),
    Case("ik.velocity_step[floating]", lambda c, q, tw: ik.velocity_step(c, q, tw, 0.05, velocity_limit=1.0),
         {"q": Arg(joints(floating), (22,)), "twist": Arg(uniform(3, 6), (3, 6))}, chain=floating,
         follows_chain=True, covers=ik.velocity_step),
    Case("ik.solve_velocity",
         lambda c, q, T: ik.solve_velocity(
             c, q, [ik.FrameTask(0, target=T), ik.PostureTask(c.q_limits.mean(-1))], 0.01,
             limits=[ik.ConfigurationLimit(), ik.VelocityLimit(2.0)]),
         {"q": Q, "T_target": Arg(poses(panda), (4, 4))}, **CH, covers=ik.solve_velocity),
    Case("ik.finite_difference_twists", lambda T: ik.finite_difference_twists(T, 0.1),
         {"T_traj": Arg(poses(panda, steps=3), (3, 4, 4))}, covers=ik.finite_difference_twists),
    Case("ik.refine_path", lambda T: ik.refine_path(T, 2), {"T_traj": Arg(poses(panda, steps=3), (3, 4, 4))},
         covers=ik.refine_path),
]

#: modules whose every public callable must have a case or an exemption
MODULES: list[str] = ["diffkin.chain", "diffkin.models", "diffkin.redundancy", "diffkin.ik",
                      "diffkin.sampling"]

_NO_TENSORS = "takes no tensor input (names, paths, mappings or counts); its bad inputs are unit-tested"
_CONTAINER = "a result container (NamedTuple/dataclass) built by the solvers, not an entry point"
_TASK = ("a task or limit of the problem description: settings whose tensors solve_velocity / solve / "
         "optimize validate against the chain (fuzzed through ik.solve_velocity; tests/test_tasks.py)")
_COST = "an ik.optimize cost term: called by optimize on the inputs optimize validated (fuzzed there)"

#: public callables without a case, with the reason
EXEMPT: dict[str, str] = {
    "diffkin.chain.KinematicChain": "abstract base: constructed by DHChain / URDFChain; its public methods "
    "have the chain.* cases above",
    "diffkin.chain.as_rigid_transform": "re-exported from diffkin.transforms (fuzzed with the geometry "
    "modules); the chain boundary that uses it, the base/tool setters, has the chain.base/chain.tool cases",
    "diffkin.models.load": _NO_TENSORS + " (tests/test_models.py)",
    "diffkin.models.load_chain": _NO_TENSORS + " (tests/test_model_loading.py)",
    "diffkin.sampling.random_configuration": _NO_TENSORS + " (a chain, a shape, a generator; "
    "tests/test_sampling.py)",
    "diffkin.models.available": _NO_TENSORS,
    "diffkin.models.info": _NO_TENSORS,
    "diffkin.models.RobotInfo": "a frozen record of what models.load reads for a name (no tensor input)",
    "diffkin.models.source": _NO_TENSORS,
    "diffkin.models.model_path": _NO_TENSORS,
    "diffkin.models.from_urdf": _NO_TENSORS + " (tests/test_urdf.py, test_urdf_xml.py)",
    "diffkin.models.URDFChain": "built from a parsed URDFTree by from_urdf (no tensor input); its methods "
    "are KinematicChain's (chain.forward_kinematics[urdf tree], ik.solve[tree])",
    "diffkin.models.from_mjcf": _NO_TENSORS + " (tests/test_mjcf.py)",
    "diffkin.models.MJCFChain": "built from a compiled MuJoCo model by from_mjcf (no tensor input); its "
    "methods are KinematicChain's (chain.forward_kinematics[mjcf floating], chain.integrate, ...)",
    "diffkin.ik.FrameTask": "velocity_step settings (an end-link index and a weight), checked there",
    "diffkin.ik.Task": _TASK, "diffkin.ik.RelativeFrameTask": _TASK, "diffkin.ik.ComTask": _TASK,
    "diffkin.ik.DampingTask": _TASK, "diffkin.ik.Limit": _TASK, "diffkin.ik.ConfigurationLimit": _TASK,
    "diffkin.ik.VelocityLimit": _TASK, "diffkin.ik.CollisionLimit": _TASK,
    "diffkin.ik.PostureTask": "velocity_step settings (q_ref, weight, gain), validated by velocity_step "
    "(tests/test_velocity_ik.py::test_typed_errors)",
    "diffkin.models.sample_workspace": _NO_TENSORS,
    "diffkin.models.parse_value": _NO_TENSORS,
    "diffkin.models.chain_from_dict": _NO_TENSORS + " (tests/test_models.py)",
    "diffkin.models.chain_to_dict": "takes a chain, returns plain Python numbers (no tensor input)",
    "diffkin.ik.CLIKResult": _CONTAINER,
    "diffkin.ik.ClosedFormSolution": _CONTAINER,
    "diffkin.ik.IKResult": _CONTAINER,
    "diffkin.ik.JointTrajectory": _CONTAINER,
    "diffkin.ik.LMConfig": "solver settings (Python numbers), no tensor input",
    "diffkin.ik.CostContext": "built by ik.optimize on validated inputs, handed to cost terms",
    "diffkin.ik.CallableCost": _COST,
    "diffkin.ik.CollisionCost": _COST + " (ik.optimize[collision])",
    "diffkin.ik.JointLimitCost": _COST,
    "diffkin.ik.ManipulabilityCost": _COST,
    "diffkin.ik.PoseCost": _COST,
    "diffkin.ik.RestPostureCost": _COST,
    "diffkin.ik.identify_structure": "takes a chain only (no tensor input); unit-tested in "
    "tests/test_ik_closed_form*.py",
}

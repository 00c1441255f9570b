"""Helpers shared by several test modules (imported as ``tests.helpers``; test modules import no other
test module). Optional references (MuJoCo, Pinocchio, coal) are imported inside the helpers that use them,
so a test that needs none of them does not pay for or skip on them."""

from __future__ import annotations

import math
import re
import sys
import threading
import warnings
from pathlib import Path

import numpy as np
import torch

from diffkin import DHChain, ik, models
from diffkin.ik import _native_solve
from diffkin.kernels import native
from diffkin.rotations import rotvec_to_matrix

DATA = Path(__file__).parent / "data"
FR3 = DATA / "urdf" / "fr3.urdf"
F64 = torch.float64
PI = math.pi


# ------------------------------------------------------------- textbook DH chains (Siciliano ch. 2)
def _rigid(g: torch.Generator) -> torch.Tensor:
    T = torch.eye(4, dtype=F64)
    T[:3, :3] = rotvec_to_matrix(torch.randn(3, generator=g, dtype=F64))
    T[:3, 3] = torch.randn(3, generator=g, dtype=F64)
    return T


def random_chain(seed: int, convention: str, types: str = "RRPRPR", base_tool: bool = True) -> DHChain:
    """A DH chain with random parameters (and random base / tool transforms) in float64."""
    g = torch.Generator().manual_seed(seed)
    n = len(types)
    a, alpha, d, theta = (torch.randn(n, generator=g, dtype=F64) for _ in range(4))
    base, tool = (_rigid(g), _rigid(g)) if base_tool else (None, None)
    return DHChain(a, alpha, d, theta, joint_types=types, convention=convention, base=base, tool=tool)


def planar3(a=(0.5, 0.4, 0.3)) -> DHChain:  # Table 2.1
    return DHChain(torch.tensor(a, dtype=F64), torch.zeros(3, dtype=F64), torch.zeros(3, dtype=F64),
                   torch.zeros(3, dtype=F64))  # fmt: skip


def anthropomorphic(a2=0.6, a3=0.45) -> DHChain:  # Table 2.4
    z = torch.zeros(3, dtype=F64)
    return DHChain(torch.tensor([0.0, a2, a3], dtype=F64), torch.tensor([PI / 2, 0, 0], dtype=F64), z, z)


def stanford(d2=0.2, d6=0.15) -> DHChain:  # Tables 2.3 + 2.5
    return DHChain(
        torch.zeros(6, dtype=F64),
        torch.tensor([-PI / 2, PI / 2, 0, -PI / 2, PI / 2, 0], dtype=F64),
        torch.tensor([0, d2, 0, 0, 0, d6], dtype=F64),
        torch.zeros(6, dtype=F64),
        joint_types="RRPRRR",
    )


def panda(dtype=F64) -> DHChain:  # Franka's modified DH table to the flange (the brief's table)
    a = [0, 0, 0, 0.0825, -0.0825, 0, 0.088]
    d = [0.333, 0, 0.316, 0, 0.384, 0, 0.107]
    alpha = [0, -PI / 2, PI / 2, PI / 2, -PI / 2, PI / 2, PI / 2]
    t = lambda x: torch.tensor(x, dtype=dtype)  # noqa: E731
    return DHChain(t(a), t(alpha), t(d), t([0.0] * 7), convention="modified")


# ------------------------------------------------------- chains the fused C kernel is checked on
def urdf_path(stem: str) -> Path:
    """A vendored real URDF (tests/data/urdf/README.md)."""
    return DATA / "urdf" / f"{stem}.urdf"


def native_chain(kind: str, dtype):
    """One of the chain kinds the fused kernel serves: DH (panda, ur5, stanford), a DH chain with base, tool
    and base_delta, a tree (allegro), mimic joints (yumi_mimic), a shared prismatic torso (tiago)."""
    if kind == "panda_base_tool":
        chain = models.load("panda", dtype=dtype)
        chain.base = torch.tensor([[0.0, -1.0, 0.0, 0.1], [1.0, 0.0, 0.0, 0.2], [0.0, 0.0, 1.0, 0.3],
                                   [0.0, 0.0, 0.0, 1.0]], dtype=dtype)
        chain.tool = torch.tensor([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0], [0.0, 1.0, 0.0, 0.1034],
                                   [0.0, 0.0, 0.0, 1.0]], dtype=dtype)
        with torch.no_grad():
            chain.base_delta.copy_(torch.tensor([0.01, -0.02, 0.0, 0.03, 0.0, -0.01], dtype=dtype))
        return chain
    if kind == "allegro":  # a tree: four fingertips, shared palm
        tips = [f"link_{i}.0_tip" for i in (3, 7, 11, 15)]
        return models.from_urdf(urdf_path("allegro_right_hand"), tips, dtype=dtype)
    if kind == "yumi_mimic":  # mimic followers: Jacobian columns summed over the coupling
        return models.from_urdf(urdf_path("yumi"), ["gripper_r_finger_r", "gripper_r_finger_l",
                                                     "gripper_l_finger_l"], dtype=dtype)
    if kind == "tiago":  # a shared prismatic torso in a two-arm tree
        return models.from_urdf(urdf_path("tiago_dual"), ["arm_left_tool_link", "arm_right_tool_link"],
                                dtype=dtype)
    return models.load(kind, dtype=dtype)  # DH: panda (modified), ur5, stanford (prismatic joint)


def c_and_torch_solve(chain, target, **kw):
    """(the C solve, the torch solve) of the same ``ik.solve`` call, without autograd; each checked to be
    served by the path it stands for."""
    with torch.no_grad():
        assert _native_solve.applies(chain, target, False)
        fused = ik.solve(chain, target, **kw)
        with native.disabled():
            assert not _native_solve.applies(chain, target, False)
            return fused, ik.solve(chain, target, **kw)


# ------------------------------------------------------------------------ MuJoCo references
def _names(m, kind, count, start=0):
    import mujoco

    return [n for i in range(start, count) if (n := mujoco.mj_id2name(m, kind, i))]


def mujoco_frames(m, d, ends, bodies):
    """Poses ``(K, 4, 4)`` and Jacobians ``(K, 6, nv_model)`` of the named bodies / sites from MuJoCo."""
    import mujoco

    obj = mujoco.mjtObj
    mujoco.mj_kinematics(m, d)
    mujoco.mj_comPos(m, d)
    T = np.tile(np.eye(4), (len(ends), 1, 1))
    J = np.zeros((len(ends), 6, m.nv))
    for k, e in enumerate(ends):
        if e in bodies:
            i = mujoco.mj_name2id(m, obj.mjOBJ_BODY, e)
            T[k, :3, 3], T[k, :3, :3] = d.xpos[i], d.xmat[i].reshape(3, 3)
            mujoco.mj_jacBody(m, d, J[k, :3], J[k, 3:], i)
        else:
            i = mujoco.mj_name2id(m, obj.mjOBJ_SITE, e)
            T[k, :3, 3], T[k, :3, :3] = d.site_xpos[i], d.site_xmat[i].reshape(3, 3)
            mujoco.mj_jacSite(m, d, J[k, :3], J[k, 3:], i)
    return T, J


def chain_of_everything(path, dtype=torch.float64):
    """(MuJoCo model, the chain to every body and site, those end names, the set of body names) of an MJCF
    file."""
    import mujoco

    from diffkin.models.mjcf import compile_mjcf

    obj = mujoco.mjtObj
    m = compile_mjcf(path)[0]
    bodies = _names(m, obj.mjOBJ_BODY, m.nbody, start=1)
    ends = bodies + _names(m, obj.mjOBJ_SITE, m.nsite)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # closed loops (connect) are reported (test_mjcf)
        chain = models.from_mjcf(path, ends, dtype=dtype)
    return m, chain, ends, set(bodies)


# ------------------------------------------------------------------------------- IK targets
TIGHT = {"position_tolerance": 1e-11, "orientation_tolerance": 1e-11}


def moved(T: torch.Tensor, xi: torch.Tensor) -> torch.Tensor:
    """T moved by a base-frame twist ξ = (δp, δω): [exp(δω) R, p + δp] (differentiable in ξ)."""
    R = rotvec_to_matrix(xi[..., 3:]) @ T[..., :3, :3]
    p = T[..., :3, 3] + xi[..., :3]
    top = torch.cat((R, p.unsqueeze(-1)), -1)
    return torch.cat((top, T[..., 3:, :].expand(*top.shape[:-2], 1, 4)), -2)


# --------------------------------------------------- the FR3 with collision geometry, and coal
#: Franka's link 1 and link 3 capsules overlap in every configuration (MoveIt's SRDF disables the pair)
FR3_SRDF = ('<robot name="fr3"><disable_collisions link1="fr3_link1_sc" link2="fr3_link3_sc" '
            'reason="Default"/></robot>')
#: the same pair as MoveIt's "Never" entry (the FR3's coarse link1 and link3 spheres always overlap)
FR3_SRDF_NEVER = ('<robot name="fr3"><disable_collisions link1="fr3_link1_sc" link2="fr3_link3_sc" '
                  'reason="Never"/></robot>')
SPHERES = [[0.45, 0.25, 0.45, 0.10], [0.40, -0.30, 0.70, 0.08]]
BOX = ([0.55, 0.0, 0.15], [0.10, 0.30, 0.02])


def fr3_robot(dtype):
    """(the FR3 chain to fr3_link8, its RobotCollision with ``FR3_SRDF``), both frozen."""
    from diffkin.collision import RobotCollision

    chain = models.from_urdf(FR3, "fr3_link8", dtype=dtype).requires_grad_(False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the FR3's meshes are not shipped: skipped with a warning
        return chain, RobotCollision.from_urdf(FR3, chain, srdf=FR3_SRDF).requires_grad_(False)


class CoalCheck:
    """The smallest distance over the checked pairs and to the obstacles (``SPHERES``, ``BOX``), by
    Pinocchio + coal; ``moving_only``: obstacle distances from the geoms that move with a joint only (the
    base's geoms left out, as the planner's checks)."""

    def __init__(self, rc, with_box=True, moving_only=False):
        import collision_reference as ref
        import pinocchio as pin

        coal = ref.coal
        self._pin, self._ref = pin, ref
        text = re.sub(r"<collision>\s*<geometry>\s*<mesh[^>]*/>\s*</geometry>\s*</collision>", "",
                      FR3.read_text())
        self.model = pin.buildModelFromXML(text)
        self.geom = pin.buildGeomFromUrdfString(self.model, text, pin.COLLISION)
        for o in self.geom.geometryObjects:  # RobotCollision's documented capsules for cylinders
            if isinstance(o.geometry, coal.Cylinder):
                o.geometry = coal.Capsule(o.geometry.radius, 2 * o.geometry.halfLength)
        index = {o.name: i for i, o in enumerate(self.geom.geometryObjects)}
        name = lambda n: "{}_{}".format(*n.rsplit("/", 1))  # noqa: E731  (Pinocchio's '<link>_<i>')
        self.pairs = [(index[name(a)], index[name(b)]) for a, b in rc.pairs]
        self.robot = [index[name(g.name)] for k, g in enumerate(rc.geoms)
                      if not (moving_only and rc.fixed[k])]
        self.obstacles = [(coal.Sphere(r), ref.placement(None, c)) for *c, r in SPHERES]
        if with_box:
            self.obstacles.append(ref.box(BOX[0], np.eye(3), BOX[1]))
        self.data, self.gdata = self.model.createData(), pin.GeometryData(self.geom)
        self.q_of = [self.model.joints[self.model.getJointId(n)].idx_q for n in rc.chain.joint_names]

    def place(self, q) -> None:
        qp = self._pin.neutral(self.model)
        qp[self.q_of] = np.asarray(q, np.float64)
        self._pin.updateGeometryPlacements(self.model, self.data, self.geom, self.gdata, qp)

    def _shape(self, i):
        M = self.gdata.oMg[i]
        return self.geom.geometryObjects[i].geometry, self._ref.placement(M.rotation, M.translation)

    def min_distance(self, q) -> float:
        """Over the checked pairs and from every robot geom to every obstacle."""
        self.place(q)
        d = [self._ref.distance(*self._shape(i), *self._shape(j)) for i, j in self.pairs]
        d += [self._ref.distance(*self._shape(i), *o) for i in self.robot for o in self.obstacles]
        return min(d)

    def min_self_distance(self, q) -> float:
        """Over the checked pairs only."""
        self.place(q)
        return min(self._ref.distance(*self._shape(i), *self._shape(j)) for i, j in self.pairs)


# ------------------------------------------------- the G1 (Menagerie MJCF) with feet, hands and its CoM
G1_MJCF = DATA / "mjcf" / "unitree_g1" / "g1.xml"
#: the feet and the hands: the FrameTasks' end links, in this order
G1_ENDS = ["left_ankle_roll_link", "right_ankle_roll_link", "left_zero_link", "right_zero_link"]
#: the finger leaves, so that the chain holds every body (the centre of mass moves with every joint)
G1_LEAVES = ["left_two_link", "left_four_link", "left_six_link", "right_two_link", "right_four_link",
             "right_six_link"]


def se3_exp(xi: torch.Tensor) -> torch.Tensor:
    """exp of twists ξ = [v; ω] ``(..., 6)`` -> ``(..., 4, 4)``: the reference, the matrix exponential of
    [[ω]×, v; 0, 0] (mink's ``SE3.exp`` and diffkin's log both use this ordering)."""
    xi = torch.as_tensor(xi, dtype=F64) if not isinstance(xi, torch.Tensor) else xi
    M = torch.zeros(*xi.shape[:-1], 4, 4, dtype=xi.dtype)
    w, v = xi[..., 3:], xi[..., :3]
    M[..., 0, 1], M[..., 0, 2], M[..., 1, 2] = -w[..., 2], w[..., 1], -w[..., 0]
    M[..., 1, 0], M[..., 2, 0], M[..., 2, 1] = w[..., 2], -w[..., 1], w[..., 0]
    M[..., :3, 3] = v
    return torch.linalg.matrix_exp(M)


def g1_com_robot(dtype=F64):
    """(the compiled MuJoCo model, the chain of every body to ``G1_ENDS + G1_LEAVES``, frozen)."""
    from diffkin.models.mjcf import compile_mjcf

    model = compile_mjcf(G1_MJCF)[0]
    return model, models.from_mjcf(G1_MJCF, G1_ENDS + G1_LEAVES, dtype=dtype).requires_grad_(False)


def g1_com_case(model, chain, seed: int, feet: float = 1e-3, hands: float = 0.03, com=None, frame=None):
    """(qpos, q, tasks) of the whole-body case: q near the model's qpos0 (normal, σ = 0.05, within the limits
    by 0.01); tasks = [ComTask (the CoM pulled by (0.02, -0.01, -0.03), costs (5, 5, 1)), four FrameTasks
    (``G1_ENDS``: feet moved by normal twists of scale ``feet``, hands of scale ``hands``, costs 10 / 1),
    PostureTask (qpos0, cost 0.1)]. ``com`` / ``frame``: further keyword arguments of those tasks."""
    rng = np.random.default_rng(seed)
    qpos = model.qpos0.copy()
    qpos[7:] += rng.normal(size=model.nq - 7) * 0.05
    lo, hi = model.jnt_range[1:, 0], model.jnt_range[1:, 1]
    qpos[7:] = np.clip(qpos[7:], lo + 0.01, hi - 0.01)
    q = torch.tensor(qpos[chain.qpos_index()])
    T = chain.forward_kinematics(q)
    com_target = chain.center_of_mass(q) + torch.tensor([0.02, -0.01, -0.03], dtype=F64)
    tasks = [ik.ComTask(com_target, cost=torch.tensor([5.0, 5.0, 1.0], dtype=F64), **(com or {}))]
    for k in range(len(G1_ENDS)):
        move = torch.tensor(rng.normal(size=6) * (hands if k >= 2 else feet))
        tasks.append(ik.FrameTask(k, target=T[k] @ se3_exp(move), position_cost=10.0, orientation_cost=1.0,
                                  **(frame or {})))
    tasks.append(ik.PostureTask(torch.tensor(model.qpos0[chain.qpos_index()]), cost=0.1))
    return qpos, q, tasks


def g1_mink_tasks(model, tasks) -> list:
    """mink's ComTask, FrameTasks and PostureTask with the targets, costs, gains and dampings of
    :func:`g1_com_case`'s ``tasks``."""
    import mink

    com = tasks[0]
    mc = mink.ComTask(cost=com.cost.numpy(), gain=com.gain, lm_damping=com.lm_damping)
    mc.set_target(com.target.numpy())
    out = [mc]
    for name, t in zip(G1_ENDS, tasks[1:1 + len(G1_ENDS)]):
        ft = mink.FrameTask(name, "body", position_cost=t.position_cost, orientation_cost=t.orientation_cost,
                            gain=t.gain, lm_damping=t.lm_damping)
        ft.set_target(mink.SE3.from_matrix(t.target.numpy()))
        out.append(ft)
    pt = mink.PostureTask(model, cost=tasks[-1].cost)
    pt.set_target(model.qpos0)
    return out + [pt]


def in_threads(call, n_threads: int = 4) -> list:
    """``call(k)`` for k = 0 .. n_threads - 1, each in its own thread, all started together and switching
    every microsecond (so first-use work and shared call structs interleave), without autograd (grad mode is
    per thread); the results in order of finishing. An exception in a thread is raised here, not lost."""
    out: list = []
    errors: list = []
    barrier = threading.Barrier(n_threads, timeout=600)

    def work(k):
        try:
            barrier.wait()
            with torch.no_grad():
                out.append(call(k))
        except Exception as e:  # noqa: BLE001 - raised below
            errors.append(e)

    old = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)
    try:
        threads = [threading.Thread(target=work, args=(k,)) for k in range(n_threads)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    finally:
        sys.setswitchinterval(old)
    if errors:
        raise errors[0]
    return out


def stand_in_compiler(directory: Path) -> str:
    """A C compiler stand-in (for ``CC``) in ``directory`` that writes to its ``-o`` argument the library this
    session built (``native.build()``, compiled once here): the library's whole build path runs in a
    subprocess (announcement, compiler call, atomic rename, load, ABI check) without paying for a real
    compile there (about 35 s on 2 cores; the session's build, and ``make test``'s ``python -m
    diffkin.kernels`` before the suite, are the real ones)."""
    built = native.build()
    cc = Path(directory) / "cc"
    cc.write_text(f"#!{sys.executable}\nimport shutil, sys\n"
                  f"shutil.copyfile({str(built)!r}, sys.argv[sys.argv.index('-o') + 1])\n")
    cc.chmod(0o755)
    return str(cc)

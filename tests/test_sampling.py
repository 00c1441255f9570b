"""The one configuration sampler (diffkin.sampling): the uniform-to-configuration map against closed forms
(the Haar measure on S³), one draw for every caller (chain, IK seeds, RandomJoints, calibration), and
collision-free sampling re-checked by coal with the geoms placed by Pinocchio (never by the code under
test)."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch

from diffkin import models
from diffkin.errors import ModelError, OptionError, SamplingError, ShapeError
from diffkin.io.data import RandomJoints, open_joint_source
from diffkin.kernels.configuration import ConfigurationSpace
from diffkin.sampling import configuration_from_uniform, random_configuration
from tests.helpers import FR3_SRDF_NEVER

scipy_stats = pytest.importorskip("scipy.stats")
F64 = torch.float64
BALLS = "tests/data/mjcf_extra/joint_kinds.xml"


def test_shoemake_map_is_the_haar_measure():
    """Rotation angles θ = 2 acos η of uniform rotations have the CDF (θ − sin θ)/π; each quaternion
    component has E[x²] = 1/4; the scalars are lower + (upper − lower) u exactly."""
    space = ConfigurationSpace(["R", "S", "P"])
    u = torch.rand(40000, space.n_uniform, generator=torch.Generator().manual_seed(0), dtype=F64)
    lo, hi = torch.tensor([-1.0, 0.5], dtype=F64), torch.tensor([2.0, 0.75], dtype=F64)
    q = space.from_uniform(lo, hi, u)
    assert q.shape == (40000, 6) and space.n_uniform == 5
    torch.testing.assert_close(q[:, 0], -1.0 + 3.0 * u[:, 0], atol=0, rtol=0)
    torch.testing.assert_close(q[:, 5], 0.5 + 0.25 * u[:, 1], atol=0, rtol=0)  # scalars first in u
    quat = q[:, 1:5]
    torch.testing.assert_close(quat.norm(dim=-1), torch.ones(40000, dtype=F64), atol=1e-14, rtol=0)
    assert (quat[:, 0] >= 0).all()
    theta = (2 * torch.acos(quat[:, 0].clamp(max=1.0))).numpy()
    assert scipy_stats.kstest(theta, lambda t: (t - np.sin(t)) / np.pi).pvalue > 1e-3
    np.testing.assert_allclose((quat**2).mean(0).numpy(), 0.25, atol=0.01)
    assert np.abs(quat[:, 1:].mean(0).numpy()).max() < 0.01  # the rotation axis has no preferred direction


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_one_draw_for_one_dof_chains(dtype):
    """A 1-DOF chain's samples are lower + (upper − lower) · torch.rand(*shape, n) of the generator (the
    draw the pinned seeds of the other tests rely on), within the limits, in the chain's dtype."""
    chain = models.load("panda", dtype=dtype)
    q = chain.random_configuration((3, 4), generator=torch.Generator().manual_seed(7))
    lo, hi = chain.lower_upper()
    u = torch.rand(3, 4, 7, generator=torch.Generator().manual_seed(7), dtype=dtype)
    assert q.dtype == dtype and q.shape == (3, 4, 7)
    torch.testing.assert_close(q, lo + (hi - lo) * u, atol=0, rtol=0)
    assert chain.within_limits(q).all()
    torch.testing.assert_close(configuration_from_uniform(chain, u), q, atol=0, rtol=0)


def test_random_joints_and_ik_seeds_use_the_one_sampler():
    """RandomJoints rows are the sampler's map of PCG64 uniforms (row-addressable, chunk-independent) and
    give unit quaternions on a chain with ball and free joints; IK's seeds map back into the ranges."""
    from diffkin.ik._kernel import JointMap

    mj = models.from_mjcf(BALLS, _ends(), dtype=F64)
    space = mj.configuration_space
    src = RandomJoints(50, seed=3).source(mj)
    whole = np.concatenate(list(src.chunks(50)))
    parts = np.concatenate(list(src.chunks(7)))
    np.testing.assert_array_equal(whole, parts)
    u = np.random.Generator(np.random.PCG64(3)).random((50, space.n_uniform))
    np.testing.assert_array_equal(whole, configuration_from_uniform(mj, torch.from_numpy(u)).numpy())
    with pytest.raises(ShapeError, match="u of shape"):
        configuration_from_uniform(mj, torch.rand(3, space.n_uniform + 1, dtype=F64))
    for iq in space.quaternion_index():
        np.testing.assert_allclose(np.linalg.norm(whole[:, list(iq)], axis=1), 1.0, atol=1e-14)
    joints = open_joint_source(RandomJoints(5, seed=1), mj.nq, mj)
    assert joints.shape == (5, mj.nq)
    # IK seeds: u = asin(2r − 1) on bounded joints, so q_of_u(sample_u) is uniform within the limits
    panda = models.load("panda", dtype=F64)
    jm = JointMap(panda, F64, "cpu", respect_limits=True)
    qs = jm.q_of_u(jm.sample_u(20000, torch.Generator().manual_seed(2))).T
    lo, hi = panda.lower_upper()
    r = ((qs - lo) / (hi - lo)).numpy()
    assert ((r >= 0) & (r <= 1)).all()
    assert min(scipy_stats.kstest(r[:, j], "uniform").pvalue for j in range(7)) > 1e-4


def _ends():
    import mujoco

    m = mujoco.MjModel.from_xml_path(BALLS)
    leaves = {b for b in range(1, m.nbody)} - {int(m.body_parentid[b]) for b in range(1, m.nbody)}
    return [m.body(b).name for b in sorted(leaves)]


# ---------------------------------------------------------------------------------------- collisions
class _Rule:
    """A duck-typed collision object: 'free' where q₁ > 0.5 (half-open), counting its calls."""

    def __init__(self):
        self.calls = 0

    def min_distance(self, q, world=None):
        self.calls += 1
        return q[..., 0] - 0.5


def test_rejection_with_a_duck_typed_object_and_its_errors():
    chain = models.load("panda", dtype=F64)
    rule = _Rule()
    q = chain.random_configuration((6, 5), generator=torch.Generator().manual_seed(0), collision=rule)
    assert q.shape == (6, 5, 7) and (q[..., 0] >= 0.5).all() and chain.within_limits(q).all()
    assert rule.calls <= 3  # batches sized by the acceptance rate, not one row at a time
    again = chain.random_configuration((6, 5), generator=torch.Generator().manual_seed(0), collision=_Rule())
    torch.testing.assert_close(q, again, atol=0, rtol=0)  # reproducible for a seed
    q2 = chain.random_configuration(40, generator=torch.Generator().manual_seed(1), collision=rule,
                                    margin=0.3)
    assert (q2[:, 0] >= 0.8).all()
    with pytest.raises(SamplingError, match="found 0 of 10"):
        chain.random_configuration(10, collision=rule, margin=5.0, max_rounds=2)
    q3, ok = chain.random_configuration(10, collision=rule, margin=5.0, max_rounds=2, return_mask=True)
    assert q3.shape == (10, 7) and ok.shape == (10,) and not ok.any() and chain.within_limits(q3).all()
    q4, ok4 = chain.random_configuration((2, 3), return_mask=True)
    assert ok4.all() and q4.shape == (2, 3, 7)
    assert chain.random_configuration(0, collision=rule).shape == (0, 7)
    with pytest.raises(ModelError, match="world= needs collision="):
        chain.random_configuration(3, world=object())
    with pytest.raises(ModelError, match="min_distance"):
        chain.random_configuration(3, collision=object())
    with pytest.raises(OptionError, match="margin"):
        chain.random_configuration(3, collision=rule, margin=-1.0)
    with pytest.raises(OptionError, match="max_rounds"):
        random_configuration(chain, 3, collision=rule, max_rounds=0)


def test_collision_free_samples_rechecked_by_coal():
    """FR3 (Franka's spheres and cylinders): every sample drawn with collision= / world= / margin= is, by
    coal with the geoms placed by Pinocchio, at least ``margin`` from every checked pair and obstacle;
    plain samples of the same robot do collide (so the check has something to reject)."""
    pytest.importorskip("pinocchio")
    import collision_reference as ref
    from test_collision_robot import FR3, _Pinocchio

    from diffkin.collision import RobotCollision, World

    chain = models.from_urdf(FR3, "fr3_link8", dtype=F64)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rc = RobotCollision.from_urdf(FR3, chain, srdf=FR3_SRDF_NEVER)
    pref = _Pinocchio(FR3.read_text(), chain, rc.geoms)
    world = World(spheres=[[0.45, 0.0, 0.45, 0.12], [0.0, 0.4, 0.3, 0.08]], dtype=F64)
    obstacles = [ref.capsule(s[:3], s[:3], s[3]) for s in world.spheres.numpy()]
    margin = 0.01

    def coal_min(q):
        out = []
        for row in q.numpy():
            pref.place(row)
            d = [ref.distance(*pref.shape(a), *pref.shape(b)) for a, b in rc.pairs]
            d += [ref.distance(*pref.shape(g.name), *o) for g in rc.geoms for o in obstacles]
            out.append(min(d))
        return np.array(out)

    plain = chain.random_configuration(150, generator=torch.Generator().manual_seed(4))
    assert (coal_min(plain) < margin).mean() > 0.2
    q = chain.random_configuration(150, generator=torch.Generator().manual_seed(4), collision=rc, world=world,
                                   margin=margin)
    assert q.shape == (150, chain.nq) and chain.within_limits(q).all()
    assert coal_min(q).min() >= margin - 1e-8
    q_self = chain.random_configuration(100, generator=torch.Generator().manual_seed(5), collision=rc)
    pref_min = []
    for row in q_self.numpy():
        pref.place(row)
        pref_min.append(min(ref.distance(*pref.shape(a), *pref.shape(b)) for a, b in rc.pairs))
    assert min(pref_min) >= -1e-8
    assert math.isfinite(min(pref_min))


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("gen_device", ["cpu", "cuda"])
def test_on_cuda(gen_device):
    """The samples on the chain's device (either generator device), the rejection on the GPU, the same
    values as on the CPU for a CPU generator."""
    cpu = models.from_mjcf(BALLS, _ends(), dtype=F64)
    chain = cpu.copy().to("cuda")  # Module.to moves in place: keep the CPU chain for the comparison
    g = torch.Generator(device=gen_device).manual_seed(0)
    q = chain.random_configuration(500, generator=g, collision=_Rule(), margin=0.1)
    assert q.device.type == "cuda" and (q[:, 0] >= 0.6).all()
    if gen_device == "cpu":
        q_cpu = cpu.random_configuration(500, generator=torch.Generator().manual_seed(0), collision=_Rule(),
                                         margin=0.1)
        torch.testing.assert_close(q.cpu(), q_cpu, atol=1e-12, rtol=0)
    u = torch.rand(7, chain.configuration_space.n_uniform, dtype=F64, device="cuda")
    assert configuration_from_uniform(chain, u).device.type == "cuda"

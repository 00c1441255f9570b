"""CPU stand-ins for what the CUDA tests guard (they skip on every machine without a GPU).

Those tests check three things: every output lies on the input's device in its dtype, the values equal the
CPU's, and nothing is made on the default device and mixed with the inputs (which raises on CUDA). A CUDA
device differs from the CPU for this library in two ways, and :func:`as_on_cuda` reproduces both on the CPU:

* the native C kernels serve CPU tensors only, so CUDA runs the torch kernels: they are turned off
  (``native.disabled()``), and the values are compared with the ordinary CPU call (native where it serves);
* a tensor made without ``device=`` lands on the CPU, not on the inputs' device: the default device is
  made ``meta`` for the call, so such a tensor is a meta tensor, and meeting the (CPU) inputs raises just as
  a CPU tensor meeting CUDA inputs does (a 0-dim one on the wrong side too), or it reaches the output on
  ``meta`` and the device check fails. :func:`test_the_stand_in_catches_what_cuda_would` shows both.

Each test names the CUDA test it stands in for; the CUDA tests stay (they also check the kernels' CUDA
arithmetic). Host-side tensors (masks, parsed model numbers, CPU random streams) say ``device="cpu"``: the
stand-in cannot tell a tensor made on the default device on purpose from a misplaced one. Not stood in:
``test_bench_gpu`` (CUDA graphs and ``torch.compile`` on the GPU) and test_collision_meshes
``test_mesh_sets_on_cuda_match_cpu`` (the mesh robot's files live with its test). The newer modules
(motion planning, time_optimal, cylinders and convex meshes, World.stack and scenes, retargeting, camera
calibration, velocity IK with tasks, the vector envs) have their stand-ins and CUDA twins in
test_device_standin_motion.py.
"""

from __future__ import annotations

import warnings

import pytest
import torch
from helpers import F64, FR3, random_chain, urdf_path

import diffkin.rotations as rot
import diffkin.trajectories as tr
import diffkin.transforms as tf
from benchmarks.cuda_smoke import outputs
from diffkin import models
from diffkin.collision import RobotCollision, World, box, box_box, capsule_box, capsule_capsule
from diffkin.errors import DTypeError
from diffkin.ik import solve
from diffkin.ik.analytic import closed_form
from diffkin.jacobian import forward_kinematics_and_jacobian, jacobian_dot_qdot
from diffkin.kernels import native
from diffkin.sampling import configuration_from_uniform


def as_on_cuda(f):
    """``f()`` as a CUDA device runs it, on the CPU (module doc)."""
    with native.disabled(), torch.device("meta"):
        return f()


def check_as_on_cuda(f, atol=1e-10, values=True):
    """The outputs of :func:`as_on_cuda` ``(f)`` on the CPU, in the dtypes and (``values``) with the values of
    the ordinary call."""
    out = outputs(as_on_cuda(f))  # first: what f caches on first use is made under the stand-in
    ref = outputs(f())
    assert len(out) == len(ref) > 0
    for o, r in zip(out, ref):
        assert o.device.type == "cpu" and o.dtype == r.dtype, (o.device, o.dtype, r.dtype)
        if values:
            torch.testing.assert_close(o.detach(), r.detach(), atol=atol, rtol=0)
    return out


def test_the_stand_in_catches_what_cuda_would():
    """A tensor made without ``device=`` and mixed with the inputs raises; one returned as is fails the
    device check (what the CUDA tests catch); made on the inputs' device, all is well."""
    x = torch.rand(4, 3, dtype=F64)
    with pytest.raises(RuntimeError, match="device"):
        as_on_cuda(lambda: x + torch.zeros(3, dtype=F64))
    with pytest.raises(RuntimeError, match="device"):
        as_on_cuda(lambda: x * torch.tensor(2.0, dtype=F64))  # CPU tensors with a 0-dim CUDA one: raises
    with pytest.raises(AssertionError):
        check_as_on_cuda(lambda: torch.eye(3, dtype=F64))
    check_as_on_cuda(lambda: x + torch.zeros(3, dtype=F64, device=x.device))
    check_as_on_cuda(lambda: x * 2.0)  # Python numbers are fine on CUDA


def test_rotations_and_transforms():
    """Stands in for test_rotations / test_transforms ``test_cuda_device_preserved``."""
    g = torch.Generator().manual_seed(0)
    R = rot.quaternion_to_matrix(torch.randn(8, 4, generator=g, dtype=F64))
    T = tf.make_transform(R, torch.randn(8, 3, generator=g, dtype=F64))
    check_as_on_cuda(lambda: (rot.matrix_to_quaternion(R), rot.matrix_to_rotvec(R), rot.matrix_to_euler(R)))
    Q, half = rot.matrix_to_quaternion(R), torch.tensor(0.5, dtype=F64)  # inputs: made outside the call
    check_as_on_cuda(lambda: rot.quaternion_slerp(Q, Q.flip(0), half))
    check_as_on_cuda(lambda: (tf.transform_inverse(T), tf.pose_error(T, tf.compose(T, T)),
                              tf.make_transform(T[:, :3, :3], T[:, :3, 3])))


@pytest.mark.parametrize("kernel", ["matrix", "column"])
def test_chain_fk_jacobian_and_device_check(kernel):
    """Stands in for test_chain / test_jacobian ``test_cuda_matches_cpu``: FK, axes, Jacobian and J̇ q̇ of
    both FK kernels; a chain on another device than q is refused by name."""
    chain = random_chain(9, "modified")
    q = torch.rand(30, chain.n_joints, dtype=F64, generator=torch.Generator().manual_seed(1))
    forced = chain.copy()
    forced.small_batch = 10**9 if kernel == "matrix" else -1  # (as test_chain's force_kernel)
    check_as_on_cuda(lambda: (forced.forward_kinematics(q), forced.joint_axes_origins(q)[0]), atol=1e-12)
    check_as_on_cuda(lambda: (*forward_kinematics_and_jacobian(chain, q), jacobian_dot_qdot(chain, q, q)))
    c32, q32 = chain.copy().to(torch.float32), q.float()
    check_as_on_cuda(lambda: forward_kinematics_and_jacobian(c32, q32), atol=1e-5)
    with pytest.raises(DTypeError, match="meta"):
        chain.copy().to("meta").forward_kinematics(q)


def test_trees_with_balls_center_of_mass_and_sampling():
    """Stands in for test_center_of_mass ``test_cuda_matches_cpu`` and test_sampling ``test_on_cuda``: the
    G1 (free joint, quaternions) FK, centre of mass and its Jacobian with gradients; samples."""
    chain = models.load("g1", dtype=F64)
    q = chain.random_configuration((8,), generator=torch.Generator().manual_seed(13))
    check_as_on_cuda(lambda: (chain.forward_kinematics(q), chain.center_of_mass(q), chain.com_jacobian(q)))

    def grad():
        qg = q.clone().requires_grad_(True)
        (chain.center_of_mass(qg).sum() + chain.com_jacobian(qg).sum()).backward()
        return qg.grad

    assert torch.isfinite(check_as_on_cuda(grad)[0]).all()
    check_as_on_cuda(lambda: chain.random_configuration((50,), generator=torch.Generator().manual_seed(0)))
    g = torch.Generator().manual_seed(2)
    u = torch.rand(7, chain.configuration_space.n_uniform, dtype=F64, generator=g)
    check_as_on_cuda(lambda: configuration_from_uniform(chain, u))


def test_ik_solve_and_closed_form():
    """Stands in for test_ik_solve ``test_solve_cuda`` and test_ik_closed_form_industrial
    ``test_cuda_follows_inputs`` (float32 batch solve; the UR10's closed form)."""
    chain = models.load("panda", dtype=torch.float32)
    q = chain.random_configuration((64,), generator=torch.Generator().manual_seed(12))
    T = chain.forward_kinematics(q)
    (qs,) = check_as_on_cuda(lambda: solve(chain, T, generator=torch.Generator().manual_seed(0)).q,
                             values=False)  # (the torch and C solvers take different iterations)
    err = (chain.forward_kinematics(qs)[..., :3, 3] - T[..., :3, 3]).norm(dim=-1)
    assert (err < 1e-3).double().mean() >= 0.95
    ur10 = models.from_urdf(urdf_path("ur10"), "tool0", dtype=F64)
    q = ur10.random_configuration((20,), generator=torch.Generator().manual_seed(3))
    check_as_on_cuda(lambda: closed_form(ur10, ur10.forward_kinematics(q)).q, atol=1e-9)


def test_collision_distances_and_robot():
    """Stands in for test_collision_distances / test_collision_robot ``test_cuda_matches_cpu``: the
    primitive distances, a robot's self and world distances."""
    g = torch.Generator().manual_seed(13)
    u = lambda *s: torch.rand(*s, generator=g, dtype=F64)  # noqa: E731
    a, b, c, h, r = u(32, 3), u(32, 3), u(32, 3), 0.2 * u(32, 3), 0.1 * u(32)
    R = rot.rotvec_to_matrix(u(32, 3))
    check_as_on_cuda(lambda: (capsule_capsule(a, b, r, c, c + 0.1, r), capsule_box(a, b, r, c, R, h),
                              box_box(c, R, h, a, R.flip(0), h.flip(0))))
    chain = models.from_urdf(FR3, "fr3_link8", dtype=F64)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # meshes not shipped: skipped with a warning
        rc = RobotCollision.from_urdf(FR3, chain)
    world = World(spheres=[[0.2, 0.1, 0.5, 0.05]], boxes=box([0.3, 0, 0.3], [0.05, 0.1, 0.2], dtype=F64),
                  halfspaces=[[0, 0, 1.0, -0.01]], dtype=F64)
    q = chain.random_configuration((16,), generator=torch.Generator().manual_seed(8))
    check_as_on_cuda(lambda: (rc.self_distances(q), rc.world_distances(q, world)))


def test_vector_env():
    """Stands in for test_vector_env ``test_cuda_matches_cpu``: reset and step."""
    from diffkin.envs.vector import TorchVectorEnv

    act = torch.rand(4, 7, generator=torch.Generator().manual_seed(0)) * 2 - 1

    def run():
        env = TorchVectorEnv("diffkin/Reach-v0", 4)
        obs, _ = env.reset(seed=1)
        obs2, *_ = env.step(act)
        return obs["observation"], obs2["observation"]

    check_as_on_cuda(run, atol=1e-6)


def test_trajectories():
    """Stands in for test_trajectories ``test_cuda_outputs_stay_on_device``."""
    pts = torch.tensor([[0.0, 1.0], [0.5, -0.2], [1.0, 0.3], [0.2, 0.8]], dtype=F64)
    times = torch.tensor([0.0, 1.0, 2.5, 3.0], dtype=F64)
    t = torch.linspace(0.0, 3.0, 13, dtype=F64)
    check_as_on_cuda(lambda: [x.position for x in (
        tr.cubic_spline(pts, times, t, end="natural_virtual"), tr.trapezoidal(pts[0], pts[1], 4.2, t),
        tr.linear_parabolic_blends(pts, times, t, blend_time=0.2), tr.anticipated_segments(pts, times, t,
                                                                                            advance=0.1))])


@pytest.mark.parametrize("method", ["least_squares", "gradient", "calibrate"])
def test_calibration_batch(method):
    """Stands in for test_calibration ``test_cuda_batch``: two robots calibrated in one call by each method;
    and ``calibrate`` of one (its cross-validation folds drawn from a CPU generator)."""
    from diffkin.calibration import calibrate, calibrate_batch

    nominal = models.load("ur5", dtype=F64)
    true = nominal.copy()
    with torch.no_grad():
        for k, p in enumerate((true.a, true.d)):  # a robot ~1 mm off its nominal link lengths and offsets
            p.add_(1e-3 * torch.randn(p.shape, generator=torch.Generator().manual_seed(k), dtype=F64))
    q = nominal.random_configuration((24,), generator=torch.Generator().manual_seed(65))
    with torch.no_grad():
        T = true.forward_kinematics(q)
    if method == "calibrate":
        res = check_as_on_cuda(lambda: calibrate(nominal, q, T, progress=False).chain.forward_kinematics(q)
                               .detach(), atol=1e-8)
    else:
        res = check_as_on_cuda(lambda: [r.chain.forward_kinematics(q).detach() for r in calibrate_batch(
            nominal, q.expand(2, -1, -1), T.expand(2, -1, -1, -1), method=method, progress=False)], atol=1e-8)
    assert (res[0] - T).abs().amax() < (nominal.forward_kinematics(q).detach() - T).abs().amax() / 10

"""DHChain (§2.8): FK against independent references, both kernels, batch shapes, dtypes, gradients, errors.

References: a plain numpy product of the book's A_i (2.52) / Craig's matrix written here from the formulas
(independent of the column kernel), Robotics Toolbox for Python (``DHRobot``) when installed,
finite differences and ``torch.autograd.gradcheck``.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from diffkin import DHChain
from diffkin.errors import ConventionError, DTypeError, ModelError, NonFiniteError, ShapeError

F64 = torch.float64


# ----------------------------------------------------------------------------------- references
def _A_standard(a, alpha, d, theta):
    ct, st, ca, sa = np.cos(theta), np.sin(theta), np.cos(alpha), np.sin(alpha)
    return np.array([[ct, -st * ca, st * sa, a * ct], [st, ct * ca, -ct * sa, a * st], [0, sa, ca, d],
                     [0, 0, 0, 1]])


def _A_modified(a, alpha, d, theta):
    Rx = np.array([[1, 0, 0, 0], [0, np.cos(alpha), -np.sin(alpha), 0], [0, np.sin(alpha), np.cos(alpha), 0],
                   [0, 0, 0, 1]])
    Tx = np.eye(4)
    Tx[0, 3] = a
    Rz = np.array([[np.cos(theta), -np.sin(theta), 0, 0], [np.sin(theta), np.cos(theta), 0, 0], [0, 0, 1, 0],
                   [0, 0, 0, 1]])
    Tz = np.eye(4)
    Tz[2, 3] = d
    return Rx @ Tx @ Rz @ Tz


def numpy_fk(table, joint_types, convention, q, base=None, tool=None, all_frames=False):
    """Reference FK for one configuration ``q (n,)`` (numpy float64)."""
    A = _A_standard if convention == "standard" else _A_modified
    T = np.eye(4) if base is None else np.asarray(base)
    frames = [T]
    for (a, alpha, d, theta), jt, qi in zip(table, joint_types, q):
        T = T @ (A(a, alpha, d, theta + qi) if jt == "R" else A(a, alpha, d + qi, theta))
        frames.append(T)
    ee = T if tool is None else T @ np.asarray(tool)
    if all_frames:
        return np.stack(frames[:-1] + [ee])
    return ee


def random_transform(rng):
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    T[:3, 3] = rng.uniform(-0.5, 0.5, 3)
    return T


def random_chain(seed, convention, with_fixed=True, dtype=F64):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 8))
    jt = "".join(rng.choice(["R", "P"], size=n, p=[0.7, 0.3]))
    table = np.stack([rng.uniform(-0.5, 0.5, n), rng.uniform(-math.pi, math.pi, n), rng.uniform(-0.5, 0.5, n),
                      rng.uniform(-math.pi, math.pi, n)], axis=1)
    base = random_transform(rng) if with_fixed else None
    tool = random_transform(rng) if with_fixed else None
    chain = DHChain(*(torch.tensor(table[:, k], dtype=dtype) for k in range(4)), joint_types=jt,
                    convention=convention, base=base, tool=tool)
    return chain, table, jt, base, tool, rng


def force_kernel(chain, kernel):
    chain.small_batch = 10**9 if kernel == "matrix" else -1
    return chain


# ------------------------------------------------------------------------------------ FK values
@pytest.mark.parametrize("convention", ["standard", "modified"])
@pytest.mark.parametrize("kernel", ["matrix", "column"])
@pytest.mark.parametrize("seed", range(6))
def test_fk_matches_numpy_reference(convention, kernel, seed):
    chain, table, jt, base, tool, rng = random_chain(seed, convention)
    force_kernel(chain, kernel)
    q = rng.uniform(-2, 2, (5, chain.n_joints))
    T = chain.forward_kinematics(torch.tensor(q, dtype=F64)).detach().numpy()
    ref = np.stack([numpy_fk(table, jt, convention, qi, base, tool) for qi in q])
    np.testing.assert_allclose(T, ref, atol=1e-12)
    frames = chain.forward_kinematics(torch.tensor(q, dtype=F64), all_frames=True).detach().numpy()
    ref_frames = np.stack([numpy_fk(table, jt, convention, qi, base, tool, all_frames=True) for qi in q])
    np.testing.assert_allclose(frames, ref_frames, atol=1e-12)


@pytest.mark.parametrize("convention", ["standard", "modified"])
@pytest.mark.parametrize("seed", range(4))
def test_fk_matches_robotics_toolbox(convention, seed):
    rtb = pytest.importorskip("roboticstoolbox")
    chain, table, jt, base, tool, rng = random_chain(100 + seed, convention)
    links = []
    for (a, alpha, d, theta), t in zip(table, jt):
        if convention == "standard":
            link = rtb.RevoluteDH(a=a, alpha=alpha, d=d, offset=theta) if t == "R" else \
                rtb.PrismaticDH(a=a, alpha=alpha, theta=theta, offset=d)
        else:
            link = rtb.RevoluteMDH(a=a, alpha=alpha, d=d, offset=theta) if t == "R" else \
                rtb.PrismaticMDH(a=a, alpha=alpha, theta=theta, offset=d)
        links.append(link)
    robot = rtb.DHRobot(links, base=base, tool=tool)
    q = rng.uniform(-2, 2, (4, chain.n_joints))
    ours = chain.forward_kinematics(torch.tensor(q, dtype=F64)).detach().numpy()
    for qi, Ti in zip(q, ours):
        np.testing.assert_allclose(Ti, robot.fkine(qi).A, atol=1e-12)


def test_two_link_closed_form_and_base_tool_composition():
    """(2.49)-style closed form of a planar 2R arm, and base/tool (2.51) as pre/post products."""
    chain = DHChain([0.7, 0.4], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0], dtype=F64)
    q = torch.tensor([[0.3, -1.1], [2.0, 0.5]], dtype=F64)
    T = chain.forward_kinematics(q)
    q1, q12 = q[:, 0], q.sum(-1)
    px = 0.7 * torch.cos(q1) + 0.4 * torch.cos(q12)
    py = 0.7 * torch.sin(q1) + 0.4 * torch.sin(q12)
    torch.testing.assert_close(T[:, 0, 3], px)
    torch.testing.assert_close(T[:, 1, 3], py)
    torch.testing.assert_close(T[:, 0, 0], torch.cos(q12))
    rng = np.random.default_rng(0)
    base, tool = torch.tensor(random_transform(rng)), torch.tensor(random_transform(rng))
    chain2 = DHChain([0.7, 0.4], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0], base=base, tool=tool, dtype=F64)
    torch.testing.assert_close(chain2.forward_kinematics(q), base @ T @ tool)


# ---------------------------------------------------------------------------------- batch shapes
@pytest.mark.parametrize("convention", ["standard", "modified"])
@pytest.mark.parametrize("shape", [(), (1,), (7,), (40,), (3, 5), (2, 3, 9)])
def test_batch_shapes_and_kernels_agree(convention, shape):
    chain, *_ = random_chain(7, convention)
    q = torch.rand(*shape, chain.n_joints, dtype=F64) * 4 - 2
    outs = {}
    for kernel in ("matrix", "column"):
        force_kernel(chain, kernel)
        T = chain.forward_kinematics(q)
        F = chain.forward_kinematics(q, all_frames=True)
        axes, origins, T2 = chain.joint_axes_origins(q)
        assert T.shape == (*shape, 4, 4) and F.shape == (*shape, chain.n_joints + 1, 4, 4)
        assert axes.shape == origins.shape == (*shape, chain.n_joints, 3)
        torch.testing.assert_close(T2, T)
        torch.testing.assert_close(F[..., -1, :, :], T)
        outs[kernel] = (T, F, axes, origins)
    for a, b in zip(outs["matrix"], outs["column"]):
        torch.testing.assert_close(a, b, atol=1e-12, rtol=0)
    flat = chain.forward_kinematics(q.reshape(-1, chain.n_joints))
    torch.testing.assert_close(flat.reshape(*shape, 4, 4), outs["column"][0])


@pytest.mark.parametrize("kernel", ["matrix", "column"])
def test_planar_all_frames_and_axes_broadcast(kernel):
    """Columns that do not depend on q (z of a planar arm) must still broadcast to the batch."""
    chain = force_kernel(DHChain([0.5] * 3, [0.0] * 3, [0.0] * 3, [0.0] * 3), kernel)
    q = torch.rand(64, 3)
    F = chain.forward_kinematics(q, all_frames=True)
    axes, origins, _ = chain.joint_axes_origins(q)
    assert F.shape == (64, 4, 4, 4)
    torch.testing.assert_close(axes, torch.tensor([0.0, 0.0, 1.0]).expand(64, 3, 3))
    torch.testing.assert_close(origins, F[:, :3, :3, 3])


@pytest.mark.parametrize("convention", ["standard", "modified"])
def test_joint_axes_origins_are_the_jacobian_frames(convention):
    """Standard DH: joint i on z_{i-1}, p_{i-1} (3.30); modified: on z_i, p_i; checked against autograd."""
    chain, *_ = random_chain(11, convention)
    q = torch.rand(3, chain.n_joints, dtype=F64)
    F = chain.forward_kinematics(q, all_frames=True)
    axes, origins, T = chain.joint_axes_origins(q)
    k = 0 if convention == "standard" else 1
    n = chain.n_joints
    if convention == "standard":
        torch.testing.assert_close(axes, F[:, k : k + n, :3, 2])
        torch.testing.assert_close(origins, F[:, k : k + n, :3, 3])
    # d p_e / d q_i = z × (p_e - p) (revolute) or z (prismatic), whatever the convention
    J = torch.autograd.functional.jacobian(lambda x: chain.forward_kinematics(x)[:3, 3], q[0])
    rev = chain.revolute_mask.bool()
    lin = torch.where(rev[:, None], torch.linalg.cross(axes[0], T[0, :3, 3] - origins[0], dim=-1), axes[0])
    torch.testing.assert_close(J.T, lin, atol=1e-12, rtol=0)


@pytest.mark.parametrize("convention", ["standard", "modified"])
def test_constant_table_path_matches_autograd_path(convention):
    """Without gradients w.r.t. the table the kernel uses it as constants (special angles become swaps):
    same frames as the differentiable path; in-place parameter updates are picked up."""
    rng = np.random.default_rng(5)
    special = [0.0, math.pi / 2, -math.pi / 2, math.pi, 0.3]
    n = 8
    chain = DHChain(rng.uniform(-1, 1, n) * (rng.random(n) > 0.4), rng.choice(special, n),
                    rng.uniform(-1, 1, n) * (rng.random(n) > 0.4), rng.choice(special, n),
                    joint_types="RRPRRPRR", convention=convention, base=random_transform(rng), dtype=F64,
                    learnable=True)
    force_kernel(chain, "column")
    q = torch.rand(50, n, dtype=F64)
    with_grad = chain.forward_kinematics(q)
    axes_g, origins_g, _ = chain.joint_axes_origins(q)
    assert chain._state_key() is None  # autograd needs the table
    with torch.no_grad():
        plan = chain._segments(per_joint=True)
        fixed = plan.post if convention == "standard" else plan.pre
        assert isinstance(fixed[0], tuple) and chain._segments(per_joint=True) is plan  # cached floats
        torch.testing.assert_close(chain.forward_kinematics(q), with_grad, atol=1e-14, rtol=0)
        axes, origins, _ = chain.joint_axes_origins(q)
        chain.a.add_(0.1)  # in-place update: the cached constants must follow
        moved = chain.forward_kinematics(q)
    torch.testing.assert_close(moved, chain.forward_kinematics(q), atol=1e-14, rtol=0)
    torch.testing.assert_close(axes, axes_g, atol=1e-14, rtol=0)
    torch.testing.assert_close(origins, origins_g, atol=1e-14, rtol=0)
    assert not torch.allclose(moved, with_grad)
    chain32 = chain.copy().float().requires_grad_(False)
    force_kernel(chain32, "column")
    torch.testing.assert_close(chain32.forward_kinematics(q.float()).double(), moved, atol=3e-6, rtol=0)


@pytest.mark.slow
def test_compile_fast_path_matches_eager():
    """chain.compile(): torch.compile of the component kernel gives the same poses (any batch > small)."""
    chain = DHChain([0.0, 0.4, 0.1], [math.pi / 2, 0.0, -math.pi / 2], [0.3, 0.0, 0.2], [0.0, 0.1, 0.0],
                    joint_types="RRP", tool=torch.tensor(random_transform(np.random.default_rng(0))))
    fast = chain.copy().compile_fk()
    for shape in [(40,), (5, 30)]:
        q = torch.rand(*shape, 3)
        with torch.no_grad():
            T = fast.forward_kinematics(q)
            torch.testing.assert_close(T, chain.forward_kinematics(q), atol=1e-6, rtol=0)
    assert fast.uncompile_fk()._compiled_fk is None


# --------------------------------------------------------------------------------------- dtypes
def test_float32_matches_float64():
    chain64, *_ = random_chain(3, "modified")
    chain32 = chain64.copy().float()
    q = torch.rand(100, chain64.n_joints, dtype=F64)
    T64 = chain64.forward_kinematics(q)
    T32 = chain32.forward_kinematics(q.float())
    assert T32.dtype == torch.float32 and chain32.a.dtype == torch.float32
    torch.testing.assert_close(T32.double(), T64, atol=2e-6, rtol=0)


def test_double_float_to_and_exact_float64_construction():
    chain = DHChain([0.5, 0.25], [math.pi / 2, 0.0], [0.1, 0.0], [0.0, 0.0], dtype=F64,
                    q_limits=[[-2.8973, 2.8973], [-1.0, 1.0]])
    assert chain.alpha[0].item() == math.pi / 2 and chain.q_limits[0, 0].item() == -2.8973
    c32 = chain.copy().float()
    assert c32.dtype == torch.float32 and c32.q_limits.dtype == torch.float32 and c32.base is None
    c64 = c32.double()
    assert c64.dtype == F64 and c64.revolute_mask.dtype == F64
    cto = chain.copy().to(torch.float32)
    assert cto.forward_kinematics(torch.zeros(2)).dtype == torch.float32
    lo, hi = DHChain([1.0], [0.0], [0.0], [0.0], dtype=F64).lower_upper()
    assert hi.item() == math.pi and lo.item() == -math.pi


def test_copy_is_independent():
    chain, *_ = random_chain(5, "standard")
    c = chain.copy()
    with torch.no_grad():
        c.a.add_(1.0)
    assert not torch.equal(c.a, chain.a)
    assert c.joint_types == chain.joint_types and c.convention == chain.convention
    assert c.metadata == chain.metadata and c.metadata is not chain.metadata


# ------------------------------------------------------------------------------------- gradients
@pytest.mark.parametrize("convention", ["standard", "modified"])
@pytest.mark.parametrize("kernel", ["matrix", "column"])
def test_gradcheck_q_and_dh_parameters(convention, kernel):
    """gradcheck (float64, finite differences) of FK w.r.t. q and each DH parameter, R and P joints."""
    from torch.func import functional_call

    rng = np.random.default_rng(21)
    table = torch.tensor(rng.uniform(-1, 1, (4, 4)), dtype=F64)
    chain = DHChain(*table.T, joint_types="RPRR", convention=convention, base=random_transform(rng),
                    tool=random_transform(rng))
    force_kernel(chain, kernel)
    q = (torch.rand(3, 4, dtype=F64) * 4 - 2).requires_grad_(True)
    names = [k for k, _ in chain.named_parameters()]
    assert set(names) == {"a", "alpha", "d", "theta", "base_delta", "tool_delta"}
    params = tuple(p.detach().clone().requires_grad_(True) for p in chain.parameters())
    with torch.no_grad():  # learnable base and tool away from their nominal value too
        params[names.index("base_delta")].copy_(torch.tensor([0.1, -0.2, 0.3, 0.4, -0.5, 0.6]))
        params[names.index("tool_delta")].copy_(torch.tensor([-0.1, 0.2, 0.05, -0.3, 0.2, 0.1]))

    def fk(q, *values):
        return functional_call(chain, dict(zip(names, values)), (q,))

    assert torch.autograd.gradcheck(fk, (q, *params))
    assert torch.autograd.gradcheck(lambda q: chain.joint_axes_origins(q)[:2], (q,))
    assert torch.autograd.gradcheck(lambda q: chain.forward_kinematics(q, all_frames=True), (q,))


def test_parameter_gradients_match_finite_differences():
    """dp_e/d(a, alpha, d, theta) by autograd (a learnable chain) vs central differences."""
    chain, *_ = random_chain(33, "standard", dtype=F64)
    chain.requires_grad_()
    q = torch.rand(chain.n_joints, dtype=F64)
    T = chain.forward_kinematics(q)
    loss = T[:3, 3].sum() + T[0, 2]
    loss.backward()
    h = 1e-6
    for name in ("a", "alpha", "d", "theta"):
        p = getattr(chain, name)
        assert p.grad is not None
        for i in range(chain.n_joints):
            with torch.no_grad():
                p[i] += h
                up = chain.forward_kinematics(q)
                p[i] -= 2 * h
                down = chain.forward_kinematics(q)
                p[i] += h
            fd = ((up[:3, 3].sum() + up[0, 2]) - (down[:3, 3].sum() + down[0, 2])) / (2 * h)
            assert abs(fd.item() - p.grad[i].item()) < 1e-7


@pytest.mark.parametrize("kernel", ["matrix", "column"])
def test_gradients_finite_at_singular_configurations(kernel):
    """q = 0 and q = pi (stretched / folded arm): FK gradients are finite (no NaN)."""
    chain = force_kernel(DHChain([0.0, 0.5, 0.5], [math.pi / 2, 0.0, 0.0], [0.0] * 3, [0.0] * 3, dtype=F64,
                                 learnable=True), kernel)
    for value in (0.0, math.pi):
        q = torch.full((20, 3), value, dtype=F64, requires_grad=True)
        chain.forward_kinematics(q).sum().backward()
        assert torch.isfinite(q.grad).all() and torch.isfinite(chain.alpha.grad).all()
        chain.zero_grad()


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("kernel", ["matrix", "column"])
def test_cuda_matches_cpu(kernel):
    chain, *_ = random_chain(9, "modified")
    force_kernel(chain, kernel)
    q = torch.rand(300, chain.n_joints, dtype=F64)
    gpu = chain.copy().to("cuda")
    force_kernel(gpu, kernel)
    T = gpu.forward_kinematics(q.cuda())
    assert T.device.type == "cuda"
    torch.testing.assert_close(T.cpu(), chain.forward_kinematics(q), atol=1e-12, rtol=0)
    with torch.no_grad():
        torch.testing.assert_close(gpu.joint_axes_origins(q.cuda())[0].cpu(), chain.joint_axes_origins(q)[0])
    with pytest.raises(DTypeError, match="cuda"):
        gpu.forward_kinematics(q)


# ---------------------------------------------------------------------------------------- errors
def test_errors_name_the_problem():
    chain = DHChain([0.5, 0.5], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0])
    with pytest.raises(ShapeError, match=r"\(\.\.\., 2\).*got \(4, 3\)"):
        chain.forward_kinematics(torch.zeros(4, 3))
    with pytest.raises(ShapeError):
        chain.forward_kinematics(torch.tensor(0.0))
    with pytest.raises(DTypeError, match="float64"):
        chain.forward_kinematics(torch.zeros(2, dtype=F64))
    # the rule of diffkin.validation: numbers, sequences and numpy arrays are converted to the chain's dtype
    torch.testing.assert_close(chain.forward_kinematics([0.1, 0.2]),
                               chain.forward_kinematics(torch.tensor([0.1, 0.2])))
    T_np = chain.forward_kinematics(np.array([[0.1, 0.2]]))  # a float64 array, a float32 chain
    assert T_np.dtype == torch.float32 and T_np.shape == (1, 4, 4)
    for bad in (torch.int64, torch.bool, torch.float16, torch.bfloat16, torch.complex64):
        with pytest.raises(DTypeError):
            chain.forward_kinematics(torch.zeros(2, dtype=bad))
    with pytest.raises(ShapeError, match=r"\(\.\.\., 2\).*got \(3, 2, 1\)"):  # no broadcast of (..., 2, 1)
        chain.within_limits(torch.zeros(3, 2, 1))
    one = DHChain([0.5], [0.0], [0.0], [0.0])
    torch.testing.assert_close(one.forward_kinematics(torch.tensor(0.3)),
                               one.forward_kinematics(torch.tensor([0.3])))
    assert chain.forward_kinematics(torch.zeros(0, 2)).shape == (0, 4, 4)
    with pytest.raises(NonFiniteError):
        chain.forward_kinematics(torch.tensor([0.0, float("nan")]))
    with pytest.raises(NonFiniteError):
        chain.joint_axes_origins(torch.tensor([[float("inf"), 0.0]]))
    assert chain.forward_kinematics(torch.tensor([3e38, 3e38])).isfinite().all()  # finite, sum overflows
    assert isinstance(ShapeError("x"), ValueError)


def test_construction_errors():
    with pytest.raises(ConventionError):
        DHChain([1.0], [0.0], [0.0], [0.0], convention="craig")
    with pytest.raises(ModelError, match="joint_types"):
        DHChain([1.0, 1.0], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0], joint_types="RX")
    with pytest.raises(ShapeError, match=r"alpha of shape \(2,\)"):
        DHChain([1.0, 1.0], [0.0], [0.0, 0.0], [0.0, 0.0])
    with pytest.raises(NonFiniteError, match="a contains NaN"):
        DHChain([1.0, float("nan")], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0])
    with pytest.raises(DTypeError, match="int64"):  # not silently truncated
        DHChain(torch.tensor([1, 2]), [0.0, 0.0], [0.0, 0.0], [0.0, 0.0])
    with pytest.raises(DTypeError, match="float32.*float64|float64.*float32"):
        DHChain(torch.ones(2), torch.zeros(2, dtype=F64), [0.0, 0.0], [0.0, 0.0])
    with pytest.raises(DTypeError):
        DHChain([1.0], [0.0], [0.0], [0.0], dtype=torch.float16)
    with pytest.raises(ModelError, match="q_limits"):
        DHChain([1.0], [0.0], [0.0], [0.0], q_limits=[[1.0, -1.0]])
    with pytest.raises(ModelError, match="rigid"):
        DHChain([1.0], [0.0], [0.0], [0.0], base=2 * torch.eye(4))
    with pytest.raises(ShapeError, match=r"tool of shape \(\.\.\., 4, 4\), got \(3, 3\)"):
        DHChain([1.0], [0.0], [0.0], [0.0], tool=torch.eye(3))
    chain = DHChain([1.0], [0.0], [0.0], [0.0])
    with pytest.raises(NonFiniteError):
        chain.base = torch.full((4, 4), float("nan"))
    with pytest.raises(DTypeError):  # a set base follows the chain's dtype
        chain.base = torch.eye(4, dtype=F64)
    with pytest.raises(ModelError):
        DHChain([], [], [], [])


# ---------------------------------------------------------------------------------------- limits
def test_limits_sampling_and_clamping():
    lim = [[-1.0, 1.0], [0.2, 0.9], [-3.0, -0.1]]
    chain = DHChain([0.1] * 3, [0.0] * 3, [0.0] * 3, [0.0] * 3, joint_types="RPR", q_limits=lim, dtype=F64)
    g = torch.Generator().manual_seed(0)
    q = chain.random_configuration((50, 2), generator=g)
    assert q.shape == (50, 2, 3) and chain.within_limits(q).all()
    lo_t, hi_t = torch.tensor(lim, dtype=F64).unbind(-1)
    # uniform over each range: the samples spread over it (not one point, not a corner)
    span = (q.amax((0, 1)) - q.amin((0, 1))) / (hi_t - lo_t)
    assert bool((span > 0.9).all()), span
    g2 = torch.Generator().manual_seed(0)
    torch.testing.assert_close(chain.random_configuration((50, 2), generator=g2), q)
    wild = torch.tensor([5.0, -5.0, 0.0], dtype=F64)
    torch.testing.assert_close(chain.clamp_to_limits(wild), torch.tensor([1.0, 0.2, -0.1], dtype=F64))
    assert not chain.within_limits(wild)
    assert chain.within_limits(wild.new_tensor([1.0 + 1e-9, 0.5, -1.0]), tol=1e-6)
    assert not chain.within_limits(wild.new_tensor([1.0 + 1e-9, 0.5, -1.0]))
    torch.testing.assert_close(chain.clamp_to_limits(q), q)  # inside: unchanged
    with pytest.raises(NonFiniteError):  # NaN is refused, never clamped into the range
        chain.clamp_to_limits(torch.tensor([float("nan"), 0.5, -1.0], dtype=F64))
    free = DHChain([0.1, 0.1], [0.0] * 2, [0.0] * 2, [0.0] * 2, joint_types="RP")
    lo, hi = free.lower_upper()
    torch.testing.assert_close(hi, torch.tensor([math.pi, 1.0]))
    wild32 = wild[:2].float()
    torch.testing.assert_close(free.clamp_to_limits(wild32), wild32)  # no limits: the identity
    assert free.within_limits(wild32) and free.within_limits(wild32[None]).shape == (1,)


def test_dh_table_and_module_behaviour():
    chain = DHChain([1.0, 2.0], [0.1, 0.2], [0.3, 0.4], [0.5, 0.6], name="toy")
    torch.testing.assert_close(chain.dh_table()[1], torch.tensor([2.0, 0.2, 0.4, 0.6]))
    names = {n for n, _ in chain.named_parameters()}
    assert names == {"a", "alpha", "d", "theta", "base_delta", "tool_delta"}
    assert "toy" in repr(chain)
    torch.testing.assert_close(chain(torch.zeros(2)), chain.forward_kinematics(torch.zeros(2)))

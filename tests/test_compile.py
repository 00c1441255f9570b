"""torch.compile (fullgraph, no graph break), torch.func.vmap / jacrev and torch.autocast over the kernels:
FK, the geometric Jacobian, the pose error and the DLS step give eager's values inside all of them."""

from __future__ import annotations

import pytest
import torch
from torch.func import jacrev, vmap

from diffkin import models
from diffkin.ik.numerical import dls_step
from diffkin.jacobian import geometric_jacobian
from diffkin.kernels.pose_error import pose_error
from diffkin.models import from_urdf
from tests.helpers import urdf_path

F64 = torch.float64


def _p_R(T):
    return T[..., :3, 3], T[..., :3, :3]


def _functions(chain, T):
    return {
        "fk": lambda q: chain.forward_kinematics(q),
        "jacobian": lambda q: geometric_jacobian(chain, q),
        "pose_error": lambda q: pose_error(*_p_R(T), *_p_R(chain.forward_kinematics(q)))[1],
        "dls_step": lambda q: dls_step(chain, q, T),
    }


@pytest.mark.parametrize("grad", [False, True])
@pytest.mark.parametrize("batch", [4, 64])  # below and above the small-batch switch of the kernels
@pytest.mark.parametrize("name", ["fk", "jacobian", "pose_error", "dls_step"])
def test_fullgraph_compile_without_graph_break(name, batch, grad):
    torch._dynamo.reset()
    chain = models.load("panda", dtype=F64, learnable=True)  # gradients w.r.t. the geometry too
    gen = torch.Generator().manual_seed(0)
    q = chain.random_configuration((batch,), generator=gen)
    T = chain.forward_kinematics(chain.random_configuration((batch,), generator=gen)).detach()
    fn = _functions(chain, T)[name]
    compiled = torch.compile(fn, fullgraph=True, backend="aot_eager")  # fullgraph: a break raises
    with torch.set_grad_enabled(grad):
        torch.testing.assert_close(compiled(q), fn(q), atol=1e-12, rtol=0)
    if grad and name in ("fk", "dls_step"):  # gradients through the compiled graph, w.r.t. q and the geometry
        qg = q.clone().requires_grad_(True)
        compiled(qg).sum().backward()
        g_compiled, g_table = qg.grad.clone(), chain.a.grad.clone()
        qg.grad, chain.a.grad = None, None
        fn(qg).sum().backward()
        torch.testing.assert_close(g_compiled, qg.grad, atol=1e-10, rtol=0)
        torch.testing.assert_close(g_table, chain.a.grad, atol=1e-10, rtol=0)


def test_compile_of_a_tree_with_mimic_joints():
    torch._dynamo.reset()
    chain = from_urdf(urdf_path("yumi"), ["gripper_r_finger_r", "gripper_r_finger_l"], dtype=F64)
    q = chain.random_configuration((32,), generator=torch.Generator().manual_seed(1))
    fn = _functions(chain, None)["jacobian"]
    with torch.no_grad():
        torch.testing.assert_close(torch.compile(fn, fullgraph=True, backend="aot_eager")(q), fn(q),
                                   atol=1e-12, rtol=0)


def test_vmap_and_jacrev_over_fk():
    chain = models.load("ur5", dtype=F64)
    q = chain.random_configuration((6,), generator=torch.Generator().manual_seed(2))
    T = vmap(chain.forward_kinematics)(q)
    torch.testing.assert_close(T, chain.forward_kinematics(q).detach(), atol=1e-14, rtol=0)
    # d p / d q by reverse mode, per sample: the linear rows of the geometric Jacobian (3.30)
    dp = vmap(jacrev(lambda x: chain.forward_kinematics(x)[:3, 3]))(q)
    torch.testing.assert_close(dp, geometric_jacobian(chain, q)[..., :3, :].detach(), atol=1e-12, rtol=0)
    # and the geometry: a batch of tables, one per sample (functional_call under vmap)
    params = {k: v.detach().expand(6, *v.shape).clone() for k, v in chain.named_parameters()}
    params["a"][:, 1] += torch.linspace(0, 0.05, 6, dtype=F64)
    T_batch = vmap(lambda p, x: torch.func.functional_call(chain, p, (x,)))(params, q)
    moved = chain.copy()
    with torch.no_grad():
        moved.a[1] += 0.05
        torch.testing.assert_close(T_batch[-1], moved.forward_kinematics(q[-1]), atol=1e-14, rtol=0)


@pytest.mark.parametrize("fast_dtype", [torch.bfloat16, torch.float16])
@pytest.mark.parametrize("grad", [False, True])
def test_autocast_keeps_the_chain_dtype(fast_dtype, grad):
    chain = models.load("panda", dtype=torch.float32)
    for shape in [(3,), (200,)]:
        q = chain.random_configuration(shape, generator=torch.Generator().manual_seed(3))
        with torch.set_grad_enabled(grad):
            T_ref, J_ref = chain.forward_kinematics(q), geometric_jacobian(chain, q)
            with torch.autocast("cpu", dtype=fast_dtype):
                T, J = chain.forward_kinematics(q), geometric_jacobian(chain, q)
                axes = chain.joint_axes_origins(q)[0]
                assert torch.is_autocast_enabled("cpu")  # the caller's region is left as it was
        assert T.dtype == J.dtype == axes.dtype == torch.float32
        torch.testing.assert_close(T, T_ref, atol=1e-6, rtol=0)
        torch.testing.assert_close(J, J_ref, atol=1e-6, rtol=0)


@pytest.mark.slow
def test_inductor_compiles_the_jacobian():
    """The default backend (inductor: generated C++ on CPU) compiles FK + Jacobian into one graph, equal to
    eager (the tests above use aot_eager to check for graph breaks quickly)."""
    torch._dynamo.reset()
    chain = models.load("panda", dtype=torch.float32)
    q = chain.random_configuration((64,), generator=torch.Generator().manual_seed(4))
    compiled = torch.compile(lambda x: geometric_jacobian(chain, x), fullgraph=True)
    with torch.no_grad():
        torch.testing.assert_close(compiled(q), geometric_jacobian(chain, q), atol=2e-6, rtol=0)

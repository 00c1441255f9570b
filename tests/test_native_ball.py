"""Ball and free joints (the S motion) in the fused C kernel: against the torch kernels and against MuJoCo's
``mj_kinematics`` / ``mj_jacBody`` / ``mj_jacSite`` on vendored models (Menagerie's G1 with its floating
base, tests/data/mjcf_extra/joint_kinds.xml: free, ball, hinge, slide joints, several per body, a joint
equality), every body and site, in float64 and float32; non-unit and zero quaternions as the torch path
treats them; per-row base poses; the motion table the packer reads from the library."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from diffkin.errors import NonFiniteError
from diffkin.kernels import native
from diffkin.models import from_mjcf
from diffkin.rotations import quaternion_to_matrix

mujoco = pytest.importorskip("mujoco")
pytestmark = pytest.mark.skipif(not native.available(), reason="no C compiler: no native kernel")

from tests.helpers import chain_of_everything, mujoco_frames  # noqa: E402

DATA = Path(__file__).parent / "data"
G1 = DATA / "mjcf" / "unitree_g1" / "g1.xml"
KINDS = DATA / "mjcf_extra" / "joint_kinds.xml"
MODELS = [G1, KINDS]
TOL = {torch.float64: 1e-12, torch.float32: 5e-6}  # C against torch: rounding only


def _q(chain, shape, seed, scale=False):
    """Random configurations; ``scale``: every quaternion multiplied by a random factor in [0.2, 5]."""
    g = torch.Generator().manual_seed(seed)
    q = chain.random_configuration(shape, generator=g)
    if scale:
        for idx in chain.configuration_space.quaternion_index():
            f = 0.2 + 4.8 * torch.rand(*q.shape[:-1], 1, generator=g, dtype=q.dtype)
            q[..., list(idx)] *= f
    return q


def _torch(chain, q):
    with native.disabled(), torch.no_grad():
        return chain.forward_kinematics_and_jacobian(q)


def _c(chain, q):
    with torch.no_grad():
        assert chain._native_model(q) is not None  # the C kernel serves this call
        return chain.forward_kinematics_and_jacobian(q)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("path", MODELS, ids=lambda p: p.name)
def test_c_equals_the_torch_kernels(path, dtype):
    _, chain, ends, _ = chain_of_everything(path, dtype)
    q = _q(chain, (37,), 1)  # two full blocks of 16 and a tail
    T, J = _c(chain, q)
    Tr, Jr = _torch(chain, q)
    assert chain.nv < chain.nq and J.shape == (37, len(ends), 6, chain.nv)
    torch.testing.assert_close(T, Tr, atol=TOL[dtype], rtol=0)
    torch.testing.assert_close(J, Jr, atol=TOL[dtype], rtol=0)
    with torch.no_grad():  # FK alone, and the batch-last layout the solvers use
        torch.testing.assert_close(chain.forward_kinematics(q), Tr, atol=TOL[dtype], rtol=0)
        rows, cols = chain.batch_last(q.T.contiguous(), with_jacobian=True)
        with native.disabled():
            rows_r, cols_r = chain.batch_last(q.T.contiguous(), with_jacobian=True)
    torch.testing.assert_close(rows, rows_r, atol=TOL[dtype], rtol=0)
    for a, b in zip(cols, cols_r):
        for x, y in zip(a, b):
            torch.testing.assert_close(*torch.broadcast_tensors(x, y), atol=TOL[dtype], rtol=0)  # or (3, 1)


def _mujoco(m, qpos, ends, bodies, velocity_map):
    """Poses ``(B, K, 4, 4)`` and Jacobians ``(B, K, 6, nv)`` from MuJoCo (columns mapped to the chain's)."""
    d = mujoco.MjData(m)
    Ts, Js = [], []
    for row in qpos:
        d.qpos[:] = row
        T, J = mujoco_frames(m, d, ends, bodies)
        Ts.append(T)
        Js.append(J @ velocity_map)
    return torch.tensor(np.stack(Ts)), torch.tensor(np.stack(Js))


@pytest.mark.parametrize("path", MODELS, ids=lambda p: p.name)
def test_c_equals_mujoco_at_random_qpos(path):
    m, chain, ends, bodies = chain_of_everything(path)
    q = _q(chain, (20,), 2)
    q[:3] = _q(chain, (3,), 3, scale=True)  # non-unit quaternions: MuJoCo normalises them as well
    ref_T, ref_J = _mujoco(m, chain.to_qpos(q).numpy(), ends, bodies, chain.velocity_map().numpy())
    T, J = _c(chain, q)
    torch.testing.assert_close(T, ref_T, atol=1e-10, rtol=0)
    torch.testing.assert_close(J, ref_J, atol=1e-10, rtol=0)
    chain32 = chain_of_everything(path, torch.float32)[1]
    T32, J32 = _c(chain32, q.float())
    torch.testing.assert_close(T32.double(), ref_T, atol=2e-5, rtol=0)
    torch.testing.assert_close(J32.double(), ref_J, atol=2e-5, rtol=0)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_non_unit_zero_and_tiny_quaternions_as_the_torch_path(dtype):
    _, chain, _, _ = chain_of_everything(KINDS, dtype)
    q = _q(chain, (16,), 4)
    scaled = _q(chain, (16,), 4, scale=True)  # the same rotations, other norms
    quats = [list(i) for i in chain.configuration_space.quaternion_index()]
    zero, tiny = scaled.clone(), scaled.clone()
    zero[:, quats[1]] = 0.0  # the identity (safe_normalize's fallback)
    tiny[:, quats[0]] *= 1e-12 if dtype == torch.float64 else 1e-8  # below the threshold: the identity too
    T, J = _c(chain, scaled)
    Tu, Ju = _c(chain, q)
    torch.testing.assert_close(T, Tu, atol=10 * TOL[dtype], rtol=0)  # a quaternion's norm does not matter
    torch.testing.assert_close(J, Ju, atol=10 * TOL[dtype], rtol=0)
    for qq in (zero, tiny):
        Tc, Jc = _c(chain, qq)
        Tr, Jr = _torch(chain, qq)
        torch.testing.assert_close(Tc, Tr, atol=TOL[dtype], rtol=0)
        torch.testing.assert_close(Jc, Jr, atol=TOL[dtype], rtol=0)
        assert not torch.allclose(Tc, T, atol=1e-3)  # the identity, not the scaled rotation
    bad = q.clone()
    bad[5, quats[0][2]] = float("nan")
    with pytest.raises(NonFiniteError):
        _c(chain, bad)
    with torch.no_grad():  # unchecked: the other rows keep their values
        T_bad = chain.forward_kinematics(bad, check=False)
    torch.testing.assert_close(T_bad[torch.arange(16) != 5], Tu[torch.arange(16) != 5], atol=0, rtol=0)


def test_per_row_base_poses_on_the_c_path():
    _, chain, _, _ = chain_of_everything(G1)
    q = _q(chain, (2, 9), 5)
    g = torch.Generator().manual_seed(6)
    B = torch.eye(4, dtype=torch.float64).repeat(2, 9, 1, 1)  # robots at 18 places
    B[..., :3, :3] = quaternion_to_matrix(torch.randn(2, 9, 4, generator=g, dtype=torch.float64))
    B[..., :3, 3] = torch.randn(2, 9, 3, generator=g, dtype=torch.float64)
    with torch.no_grad():
        assert chain._native_model(q) is not None
        T = chain.forward_kinematics(q, base=B)
        T_w, J_w = chain.forward_kinematics_and_jacobian(q, base=B)
        with native.disabled():
            T_r = chain.forward_kinematics(q, base=B)
            T0, J0 = chain.forward_kinematics_and_jacobian(q)
    torch.testing.assert_close(T, T_r, atol=1e-12, rtol=0)
    torch.testing.assert_close(T, B.unsqueeze(-3) @ T0, atol=1e-12, rtol=0)
    torch.testing.assert_close(T_w, T, atol=1e-12, rtol=0)
    R = B[..., None, :3, :3]
    J_ref = torch.cat((R @ J0[..., :3, :], R @ J0[..., 3:, :]), dim=-2)
    torch.testing.assert_close(J_w, J_ref, atol=1e-12, rtol=0)


def test_threads_do_not_change_a_value():
    _, chain, _, _ = chain_of_everything(G1)
    q = _q(chain, (1500,), 7)
    with torch.no_grad():
        packed = chain._native_model(q)
    one = native.fk_jacobian(packed, q, True, threads=1)
    two = native.fk_jacobian(packed, q, True, threads=2)
    assert torch.equal(one[0], two[0]) and torch.equal(one[1], two[1])


def test_the_motion_table_comes_from_the_library(monkeypatch):
    codes = native.motion_table(native._lib)
    assert sorted(codes) == ["P", "R", "S"] and sorted(codes.values()) == [0, 1, 2]
    _, chain, _, _ = chain_of_everything(KINDS)
    topo = chain._topo
    with torch.no_grad():
        packed = chain._native_model(_q(chain, (1,), 0))
    motion = packed.ints["motion"].tolist()
    assert motion.count(codes["S"]) == sum(topo.spherical) == 3  # the free joint's S and two balls
    assert motion.count(codes["P"]) == sum(1 for s, r in zip(topo.spherical, topo.revolute) if not (s or r))
    assert not packed.euclidean and packed.n_velocities == chain.nv
    monkeypatch.setitem(native.MOTION_NV, "S", 4)  # a configuration layer the library does not speak
    with pytest.raises(native.AbiMismatch, match="motions"):
        native.motion_table(native._lib)


def test_the_single_call_path_of_a_ball_chain_matches_the_batch():
    """One q (nq,) through kernels.single: Jacobian (6, nv) equal to the batched call's row (it was
    allocated (6, nq) for chains whose q holds quaternions)."""
    chain = from_mjcf(KINDS, "palm", root_link="torso", dtype=torch.float64).requires_grad_(False)
    q = chain.random_configuration(3, generator=torch.Generator().manual_seed(2))
    T1, J1 = chain.forward_kinematics_and_jacobian(q[1])
    Tb, Jb = chain.forward_kinematics_and_jacobian(q)
    assert J1.shape == (6, chain.nv) and chain.nv != chain.nq
    torch.testing.assert_close(T1, Tb[1], rtol=0, atol=1e-13)
    torch.testing.assert_close(J1, Jb[1], rtol=0, atol=1e-13)

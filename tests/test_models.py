"""Bundled models (§2.9) against the book's closed-form direct kinematics, YAML schema, exact loading.

References: the closed forms (2.63)-(2.71), (2.74)-(2.76), (2.78) typed in from the textbook, scipy's
ZYZ Euler matrix, Robotics Toolbox's Panda and UR5 DH models (when installed), the data-sheet poses.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from diffkin import models
from diffkin.errors import ModelError
from diffkin.models import load, parse_value

F64 = torch.float64
NAMES = ["anthropomorphic_arm", "anthropomorphic_wrist", "dlr", "humanoid_arm", "kuka_iiwa14", "panda",
         "parallelogram", "spherical_arm", "spherical_wrist", "stanford", "three_link_planar", "ur5"]


def _q(chain, n=16, seed=0):
    return chain.random_configuration((n,), generator=torch.Generator().manual_seed(seed))


def _cs(q):
    return torch.cos(q), torch.sin(q)


def _mat(rows):
    """Stack nested lists of (B,) tensors into (B, r, c)."""
    return torch.stack([torch.stack(r, dim=-1) for r in rows], dim=-2)


# ------------------------------------------------------------------------------------- registry
def test_available_and_sources():
    assert [r.name for r in models.available(details=True) if r.format == "dh"] == NAMES
    assert set(NAMES) <= set(models.available())
    for name in NAMES:
        chain = load(name)
        assert chain.name == name and chain.q_limits is not None
        assert models.source(name) and chain.metadata["source"] == models.source(name)
    with pytest.raises(ModelError, match="unknown model 'puma'.*panda"):
        load("puma")
    with pytest.raises(ModelError, match="from_urdf"):
        load("robot.urdf")


@pytest.mark.parametrize("name", NAMES)
def test_load_dtypes_devices_and_exactness(name):
    c64 = load(name, dtype=F64, device="cpu")
    c32 = load(name, dtype=torch.float32)
    assert c64.dtype == F64 and c64.a.dtype == F64 and c64.q_limits.dtype == F64 and c64.device.type == "cpu"
    assert c32.dtype == torch.float32
    for p in ("a", "alpha", "d", "theta"):  # float32 table == float64 table rounded once
        assert torch.equal(getattr(c32, p), getattr(c64, p).float())
    q = _q(c64)
    torch.testing.assert_close(c32.forward_kinematics(q.float()).double(), c64.forward_kinematics(q),
                               atol=2e-6, rtol=0)


def test_float64_values_are_exact():
    panda = load("panda", dtype=F64)
    assert panda.alpha[1].item() == -math.pi / 2 and panda.alpha[2].item() == math.pi / 2
    assert panda.d[0].item() == 0.333 and panda.a[3].item() == 0.0825
    assert panda.q_limits[5].tolist() == [-0.0175, 3.7525]
    iiwa = load("kuka_iiwa14", dtype=F64)
    assert iiwa.q_limits[6, 1].item() == math.radians(175)
    assert load("ur5", dtype=F64).q_limits[0, 1].item() == 2 * math.pi
    assert load("humanoid_arm", dtype=F64).alpha[3].item() == math.pi / 6


# ------------------------------------------------------------------------------- closed forms
def test_three_link_planar_2_63():
    chain = load("three_link_planar", dtype=F64)
    q = _q(chain)
    c1, s1 = _cs(q[:, 0])
    c12, s12 = _cs(q[:, 0] + q[:, 1])
    c123, s123 = _cs(q.sum(-1))
    z, o = torch.zeros_like(c1), torch.ones_like(c1)
    T = _mat([[c123, -s123, z, 0.5 * (c1 + c12 + c123)], [s123, c123, z, 0.5 * (s1 + s12 + s123)],
              [z, z, o, z], [z, z, z, o]])
    torch.testing.assert_close(chain.forward_kinematics(q), T)


def test_parallelogram_closure_2_64():
    chain = load("parallelogram", dtype=F64)
    a1p, a2p, a3p = chain.a.tolist()
    a4 = chain.tool[0, 3].item()
    assert a1p == a3p  # parallelogram: a1' = a3', a2' = a1''
    a1pp = a2p
    g = torch.Generator().manual_seed(1)
    th1p, th1pp = (torch.rand(32, generator=g, dtype=F64) * 2 * math.pi - math.pi for _ in range(2))
    th2p = th1pp - th1p
    th3p = math.pi - th2p
    q = torch.stack((th1p, th2p, th3p), dim=-1)
    T = chain.forward_kinematics(q)
    c1, s1 = _cs(th1p)
    c1pp, s1pp = _cs(th1pp)
    z, o = torch.zeros_like(c1), torch.ones_like(c1)
    expected = _mat([[-c1, s1, z, a1pp * c1pp - a4 * c1], [-s1, -c1, z, a1pp * s1pp - a4 * s1],
                     [z, z, o, z], [z, z, z, o]])
    torch.testing.assert_close(T, expected)
    # closure: origin of Frame 3' (= p_e - a4 x_e, tool Tx(a4)) coincides with the tip of branch 1''
    p3 = T[:, :3, 3] - a4 * T[:, :3, 0]
    p1pp = torch.stack((a1pp * c1pp, a1pp * s1pp, z), dim=-1)
    torch.testing.assert_close(p3, p1pp)
    # and it is violated off the constraint manifold
    q_bad = q + torch.tensor([0.0, 0.3, 0.0], dtype=F64)
    T_bad = chain.forward_kinematics(q_bad)
    assert ((T_bad[:, :3, 3] - a4 * T_bad[:, :3, 0] - p1pp).norm(dim=-1) > 1e-3).all()


def test_spherical_arm_2_65():
    chain = load("spherical_arm", dtype=F64)
    q = _q(chain)
    (c1, s1), (c2, s2), d3 = _cs(q[:, 0]), _cs(q[:, 1]), q[:, 2]
    d2 = chain.d[1].item()
    z, o = torch.zeros_like(c1), torch.ones_like(c1)
    T = _mat([[c1 * c2, -s1, c1 * s2, c1 * s2 * d3 - s1 * d2], [s1 * c2, c1, s1 * s2, s1 * s2 * d3 + c1 * d2],
              [-s2, z, c2, c2 * d3], [z, z, z, o]])
    torch.testing.assert_close(chain.forward_kinematics(q), T)


def test_anthropomorphic_arm_2_66():
    chain = load("anthropomorphic_arm", dtype=F64)
    a2, a3 = chain.a[1].item(), chain.a[2].item()
    q = _q(chain)
    (c1, s1), (c2, s2), (c23, s23) = _cs(q[:, 0]), _cs(q[:, 1]), _cs(q[:, 1] + q[:, 2])
    z, o = torch.zeros_like(c1), torch.ones_like(c1)
    r = a2 * c2 + a3 * c23
    T = _mat([[c1 * c23, -c1 * s23, s1, c1 * r], [s1 * c23, -s1 * s23, -c1, s1 * r],
              [s23, c23, z, a2 * s2 + a3 * s23], [z, z, z, o]])
    torch.testing.assert_close(chain.forward_kinematics(q), T)


def _wrist_2_67(q, d6):
    (c4, s4), (c5, s5), (c6, s6) = _cs(q[:, 0]), _cs(q[:, 1]), _cs(q[:, 2])
    z, o = torch.zeros_like(c4), torch.ones_like(c4)
    return _mat([[c4 * c5 * c6 - s4 * s6, -c4 * c5 * s6 - s4 * c6, c4 * s5, c4 * s5 * d6],
                 [s4 * c5 * c6 + c4 * s6, -s4 * c5 * s6 + c4 * c6, s4 * s5, s4 * s5 * d6],
                 [-s5 * c6, s5 * s6, c5, c5 * d6], [z, z, z, o]])


def test_spherical_wrist_2_67_is_zyz_euler():
    chain = load("spherical_wrist", dtype=F64)
    q = _q(chain)
    T = chain.forward_kinematics(q)
    torch.testing.assert_close(T, _wrist_2_67(q, chain.d[2].item()))
    R_zyz = Rotation.from_euler("ZYZ", q.numpy()).as_matrix()  # (2.18)
    np.testing.assert_allclose(T[:, :3, :3].detach().numpy(), R_zyz, atol=1e-12)


def test_stanford_2_68_2_69():
    chain = load("stanford", dtype=F64)
    q = _q(chain)
    (c1, s1), (c2, s2), d3 = _cs(q[:, 0]), _cs(q[:, 1]), q[:, 2]
    (c4, s4), (c5, s5), (c6, s6) = _cs(q[:, 3]), _cs(q[:, 4]), _cs(q[:, 5])
    d2, d6 = chain.d[1].item(), chain.d[5].item()
    k = c2 * c4 * s5 + s2 * c5
    p = torch.stack((c1 * s2 * d3 - s1 * d2 + (c1 * k - s1 * s4 * s5) * d6,
                     s1 * s2 * d3 + c1 * d2 + (s1 * k + c1 * s4 * s5) * d6,
                     c2 * d3 + (-s2 * c4 * s5 + c2 * c5) * d6), dim=-1)
    u = c4 * c5 * c6 - s4 * s6
    v = s4 * c5 * c6 + c4 * s6
    n = torch.stack((c1 * (c2 * u - s2 * s5 * c6) - s1 * v, s1 * (c2 * u - s2 * s5 * c6) + c1 * v,
                     -s2 * u - c2 * s5 * c6), dim=-1)
    u2 = c4 * c5 * s6 + s4 * c6
    v2 = -s4 * c5 * s6 + c4 * c6
    s = torch.stack((c1 * (-c2 * u2 + s2 * s5 * s6) - s1 * v2, s1 * (-c2 * u2 + s2 * s5 * s6) + c1 * v2,
                     s2 * u2 + c2 * s5 * s6), dim=-1)
    a = torch.stack((c1 * k - s1 * s4 * s5, s1 * k + c1 * s4 * s5, -s2 * c4 * s5 + c2 * c5), dim=-1)
    T = chain.forward_kinematics(q)
    for col, ref in zip(range(4), (n, s, a, p)):
        torch.testing.assert_close(T[:, :3, col], ref)
    # T^0_6 = T^0_3 (2.65) T^3_6 (2.67): Frame 3 is shared
    T03 = load("spherical_arm", dtype=F64).forward_kinematics(q[:, :3])
    torch.testing.assert_close(T, T03 @ _wrist_2_67(q[:, 3:], d6))


def test_anthropomorphic_wrist_2_70_2_71():
    chain = load("anthropomorphic_wrist", dtype=F64)
    a2, d4, d6 = chain.a[1].item(), chain.d[3].item(), chain.d[5].item()
    q = _q(chain)
    (c1, s1), (c2, s2), (c23, s23) = _cs(q[:, 0]), _cs(q[:, 1]), _cs(q[:, 1] + q[:, 2])
    (c4, s4), (c5, s5), (c6, s6) = _cs(q[:, 3]), _cs(q[:, 4]), _cs(q[:, 5])
    k = c23 * c4 * s5 + s23 * c5
    p = torch.stack((a2 * c1 * c2 + d4 * c1 * s23 + d6 * (c1 * k + s1 * s4 * s5),
                     a2 * s1 * c2 + d4 * s1 * s23 + d6 * (s1 * k - c1 * s4 * s5),
                     a2 * s2 - d4 * c23 + d6 * (s23 * c4 * s5 - c23 * c5)), dim=-1)
    u = c4 * c5 * c6 - s4 * s6
    v = s4 * c5 * c6 + c4 * s6
    n = torch.stack((c1 * (c23 * u - s23 * s5 * c6) + s1 * v, s1 * (c23 * u - s23 * s5 * c6) - c1 * v,
                     s23 * u + c23 * s5 * c6), dim=-1)
    u2 = c4 * c5 * s6 + s4 * c6
    v2 = -s4 * c5 * s6 + c4 * c6
    s = torch.stack((c1 * (-c23 * u2 + s23 * s5 * s6) + s1 * v2, s1 * (-c23 * u2 + s23 * s5 * s6) - c1 * v2,
                     -s23 * u2 - c23 * s5 * s6), dim=-1)
    a = torch.stack((c1 * k + s1 * s4 * s5, s1 * k - c1 * s4 * s5, s23 * c4 * s5 - c23 * c5), dim=-1)
    T = chain.forward_kinematics(q)
    for col, ref in zip(range(4), (n, s, a, p)):
        torch.testing.assert_close(T[:, :3, col], ref)
    # with d6 = 0 the wrist point is p^0_3 of (2.66) with a3 = d4: (2.70) at ϑ3 + π/2 equals (2.66) at ϑ3
    # (§2.9.7, §2.12.4)
    arm = load("anthropomorphic_arm", dtype=F64)
    with torch.no_grad():
        arm.a[2] = d4
    q_arm = q[:, :3] - torch.tensor([0.0, 0.0, math.pi / 2], dtype=F64)
    wrist = T[:, :3, 3] - d6 * T[:, :3, 2]
    torch.testing.assert_close(wrist, arm.forward_kinematics(q_arm)[:, :3, 3])


def _dlr_2_74_2_76(q, d3, d5, d7):
    c = [None] + [torch.cos(q[:, i]) for i in range(7)]
    s = [None] + [torch.sin(q[:, i]) for i in range(7)]
    k1 = c[3] * (c[4] * c[5] * s[6] - s[4] * c[6]) + s[3] * s[5] * s[6]
    k2 = s[4] * c[5] * s[6] + c[4] * c[6]
    k3 = s[3] * (c[4] * c[5] * s[6] - s[4] * c[6]) - c[3] * s[5] * s[6]
    xd3, yd3, zd3 = c[1] * s[2], s[1] * s[2], -c[2]
    xd5 = c[1] * (c[2] * c[3] * s[4] - s[2] * c[4]) + s[1] * s[3] * s[4]
    yd5 = s[1] * (c[2] * c[3] * s[4] - s[2] * c[4]) - c[1] * s[3] * s[4]
    zd5 = c[2] * c[4] + s[2] * c[3] * s[4]
    xd7 = c[1] * (c[2] * k1 + s[2] * k2) + s[1] * k3
    yd7 = s[1] * (c[2] * k1 + s[2] * k2) - c[1] * k3
    zd7 = s[2] * (c[3] * (c[4] * c[5] * s[6] - s[4] * c[6]) + s[3] * s[5] * s[6]) - c[2] * k2
    p = torch.stack((d3 * xd3 + d5 * xd5 + d7 * xd7, d3 * yd3 + d5 * yd5 + d7 * yd7,
                     d3 * zd3 + d5 * zd5 + d7 * zd7), dim=-1)
    xa = (c[1] * c[2] * c[3] + s[1] * s[3]) * c[4] + c[1] * s[2] * s[4]
    xb = (c[1] * c[2] * c[3] + s[1] * s[3]) * s[4] - c[1] * s[2] * c[4]
    xc = c[1] * c[2] * s[3] - s[1] * c[3]
    ya = (s[1] * c[2] * c[3] - c[1] * s[3]) * c[4] + s[1] * s[2] * s[4]
    yb = (s[1] * c[2] * c[3] - c[1] * s[3]) * s[4] - s[1] * s[2] * c[4]
    yc = s[1] * c[2] * s[3] + c[1] * c[3]
    za = (s[2] * c[3] * c[4] - c[2] * s[4]) * c[5] + s[2] * s[3] * s[5]
    # (2.76) prints z_b = (s2 c3 s4 + c2 c4) s5 - s2 s3 c5; the x/y pattern (x_a s5 - x_c c5) and the
    # orthonormality of (n, s, a) need the factor of z_a instead: a misprint, corrected here.
    zb = (s[2] * c[3] * c[4] - c[2] * s[4]) * s[5] - s[2] * s[3] * c[5]
    zc = s[2] * c[3] * s[4] + c[2] * c[4]
    n = torch.stack((((xa * c[5] + xc * s[5]) * c[6] + xb * s[6]) * c[7] + (xa * s[5] - xc * c[5]) * s[7],
                     ((ya * c[5] + yc * s[5]) * c[6] + yb * s[6]) * c[7] + (ya * s[5] - yc * c[5]) * s[7],
                     (za * c[6] + zc * s[6]) * c[7] + zb * s[7]), dim=-1)
    s_ = torch.stack((-((xa * c[5] + xc * s[5]) * c[6] + xb * s[6]) * s[7] + (xa * s[5] - xc * c[5]) * c[7],
                      -((ya * c[5] + yc * s[5]) * c[6] + yb * s[6]) * s[7] + (ya * s[5] - yc * c[5]) * c[7],
                      -(za * c[6] + zc * s[6]) * s[7] + zb * c[7]), dim=-1)
    a = torch.stack(((xa * c[5] + xc * s[5]) * s[6] - xb * c[6], (ya * c[5] + yc * s[5]) * s[6] - yb * c[6],
                     za * s[6] - zc * c[6]), dim=-1)
    return n, s_, a, p


def test_dlr_2_74_2_76():
    chain = load("dlr", dtype=F64)
    q = _q(chain)
    T = chain.forward_kinematics(q)
    refs = _dlr_2_74_2_76(q, chain.d[2].item(), chain.d[4].item(), chain.d[6].item())
    for col, ref in zip(range(4), refs):
        torch.testing.assert_close(T[:, :3, col], ref)


def _np_dh(theta, d, a, alpha):
    ct, st, ca, sa = math.cos(theta), math.sin(theta), math.cos(alpha), math.sin(alpha)
    return np.array([[ct, -st * ca, st * sa, a * ct], [st, ct * ca, -ct * sa, a * st], [0, sa, ca, d],
                     [0, 0, 0, 1.0]])


def test_humanoid_arm_2_78_and_level_chest():
    chain = load("humanoid_arm", dtype=F64)
    q = _q(chain, n=8)
    q[:, 3] = -(q[:, 1] + q[:, 2])  # the chest-levelling device (§2.9.9)
    T = chain.forward_kinematics(q).detach().numpy()
    frames = chain.forward_kinematics(q, all_frames=True)
    T03 = load("anthropomorphic_arm", dtype=F64)
    with torch.no_grad():
        T03.a[1:] = 0.3
    T03 = T03.forward_kinematics(q[:, :3]).detach().numpy()  # (2.66)
    for b in range(q.shape[0]):
        qb = q[b].tolist()
        c23, s23 = math.cos(qb[1] + qb[2]), math.sin(qb[1] + qb[2])
        T3t = np.array([[c23, s23, 0, 0], [-s23, c23, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])  # book's T^3_t
        Ttr = _np_dh(0.0, 0.25, 0.0, math.pi / 6)  # the model's constant T^t_r = Tz(d4) Rx(β)
        Trh = np.eye(4)
        for i, d in enumerate([0, 0, 0.4, 0, 0.39, 0]):  # (2.72), α = π/2
            Trh = Trh @ _np_dh(qb[4 + i], d, 0.0, math.pi / 2)
        Trh = Trh @ _np_dh(qb[10], 0.0, 0.1, math.pi / 2)  # α7 = π/2, a7 = 0.1, d7 = 0
        Te = np.array([[0, 0, 1, 0], [0, 1, 0, 0], [-1, 0, 0, 0], [0, 0, 0, 1.0]])  # approach along x7
        np.testing.assert_allclose(T[b], T03[b] @ T3t @ Ttr @ Trh @ Te, atol=1e-12)
        # chest frame t stays upright: R^0_t = Rz(ϑ1) Rx(π/2), y_t vertical
        R0t = frames[b, 4, :3, :3].detach().numpy() @ Rotation.from_euler("x", -math.pi / 6).as_matrix()
        upright = Rotation.from_euler("ZX", [qb[0], math.pi / 2]).as_matrix()
        np.testing.assert_allclose(R0t, upright, atol=1e-12)


# -------------------------------------------------------------------------------------- real arms
def test_real_arm_reference_poses():
    panda = load("panda", dtype=F64).forward_kinematics(torch.zeros(7, dtype=F64))
    torch.testing.assert_close(panda[:3, 3], torch.tensor([0.088, 0.0, 0.926], dtype=F64))
    torch.testing.assert_close(panda[:3, :3], torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=F64)))
    iiwa = load("kuka_iiwa14", dtype=F64).forward_kinematics(torch.zeros(7, dtype=F64))
    iiwa_ref = torch.tensor([[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 1.306], [0, 0, 0, 1]], dtype=F64)
    torch.testing.assert_close(iiwa, iiwa_ref)
    # UR5 at q = 0: (a2 + a3, -(d4 + d6), d1 - d5)
    ur5 = load("ur5", dtype=F64).forward_kinematics(torch.zeros(6, dtype=F64))
    torch.testing.assert_close(ur5[:3, 3], torch.tensor([-0.81725, -0.19145, 0.089159 - 0.09465], dtype=F64))


@pytest.mark.parametrize("name, rtb_name", [("panda", "Panda"), ("ur5", "UR5")])
def test_real_arms_match_robotics_toolbox(name, rtb_name):
    rtb = pytest.importorskip("roboticstoolbox")
    robot = getattr(rtb.models.DH, rtb_name)()
    robot.tool = np.eye(4)  # rtb's Panda carries the hand; ours stops at the flange
    if name == "ur5":  # rtb 1.5 has d1 = 0.089459; UR's published UR5 (CB3) value is 0.089159
        robot.links[0].d = 0.089159
    chain = load(name, dtype=F64)
    q = _q(chain, n=5)
    T = chain.forward_kinematics(q).detach().numpy()
    for qb, Tb in zip(q.numpy(), T):
        np.testing.assert_allclose(Tb, robot.fkine(qb).A, atol=1e-12)


# ---------------------------------------------------------------------------------------- YAML
@pytest.mark.parametrize("value, expected", [
    (1, 1.0), (0.25, 0.25), ("pi/2", math.pi / 2), ("-pi/2", -math.pi / 2), ("0.5*pi", 0.5 * math.pi),
    ("170 deg", math.radians(170)), ("-90deg", -math.pi / 2), ("1e-3", 1e-3),
    ("(pi + 1) / 2", (math.pi + 1) / 2),
    ("2*pi/3", 2 * math.pi / 3), (" +pi ", math.pi),
])
def test_parse_value(value, expected):
    assert parse_value(value) == expected


@pytest.mark.parametrize("bad", ["__import__('os').system('true')", "pi**2", "sin(1)", "e", "1/0", "pi/",
                                 True, None, [1.0], "inf", "1e999"])
def test_parse_value_rejects(bad):
    with pytest.raises(ModelError, match="dh\\[0\\]\\.a"):
        parse_value(bad, "dh[0].a")


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_yaml_round_trip_is_exact(name, dtype, tmp_path):
    chain = load(name, dtype=dtype)
    text = chain.to_yaml(tmp_path / f"{name}.yaml")
    for again in (type(chain).from_yaml(text, dtype=dtype), load(tmp_path / f"{name}.yaml", dtype=dtype)):
        for p in ("a", "alpha", "d", "theta", "q_limits", "revolute_mask"):
            assert torch.equal(getattr(again, p), getattr(chain, p)), p
        for p in ("base", "tool"):
            assert (getattr(chain, p) is None and getattr(again, p) is None) or torch.equal(
                getattr(again, p), getattr(chain, p))
        assert (again.name, again.convention, again.joint_types) == (chain.name, chain.convention,
                                                                     chain.joint_types)
    assert type(chain).from_dict(chain.to_dict(), dtype=dtype).n_joints == chain.n_joints


def test_transform_specs_and_from_dict():
    base = {"xyz": [0.1, 0, "0.5"], "rpy": [0, 0, "pi/2"]}
    tool = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0.2]]
    chain = models.chain_from_dict({"name": "toy", "dh": [{"a": 1, "alpha": 0, "d": 0, "theta": 0}],
                                    "base": base, "tool": {"matrix": tool}}, dtype=F64)
    expected_base = torch.tensor([[0.0, -1, 0, 0.1], [1, 0, 0, 0], [0, 0, 1, 0.5], [0, 0, 0, 1]], dtype=F64)
    assert torch.equal(chain.base, expected_base)
    T = chain.forward_kinematics(torch.zeros(1, dtype=F64))
    torch.testing.assert_close(T[:3, 3], torch.tensor([0.1, 1.0, 0.7], dtype=F64))
    R = Rotation.from_euler("xyz", [0.3, -0.2, 1.1]).as_matrix()  # URDF rpy: Rz(y) Ry(p) Rx(r)
    c2 = models.chain_from_dict({"name": "t", "dh": [{"a": 1, "alpha": 0, "d": 0, "theta": 0}],
                                 "base": {"rpy": [0.3, -0.2, 1.1]}}, dtype=F64)
    np.testing.assert_allclose(c2.base[:3, :3].numpy(), R, atol=1e-15)


_GOOD = """\
name: toy
convention: standard
joint_types: RP
dh:
  - {a: 0.5, alpha: pi/2, d: 0, theta: 0}
  - {a: 0, alpha: 0, d: 0.1, theta: 0}
q_limits:
  - [-pi, pi]
  - [0, 0.5]
"""


@pytest.mark.parametrize("edit, message", [
    (("alpha: pi/2", "alpha: pi/"), r"bad\.yaml: dh\[0\]\.alpha: cannot parse 'pi/'"),
    (("alpha: pi/2", "alpha: os.system"), r"dh\[0\]\.alpha"),
    (("d: 0.1, theta: 0", "d: 0.1"), r"dh\[1\]: keys must be a, alpha, d, theta .*missing \['theta'\]"),
    (("d: 0.1, theta: 0", "d: 0.1, theta: 0, b: 1"), r"dh\[1\].*unknown \['b'\]"),
    (("joint_types: RP", "joint_types: RPR"), "joint_types: expected 2 letters"),
    (("convention: standard", "convention: craig"), "convention"),
    (("[0, 0.5]", "[0.5, 0]"), r"q_limits\[1\]: lower 0.5 must be < upper 0.0"),
    (("q_limits:", "q_limit:"), r"unknown keys \['q_limit'\]"),
    (("name: toy", "name: [toy"), "invalid YAML"),
    (("name: toy", "name: ''"), "name"),
])
def test_bad_yaml_errors_point_at_the_field(edit, message, tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text(_GOOD.replace(*edit))
    with pytest.raises(ModelError, match=message):
        load(path)


def test_bad_fixed_transforms_and_misc_errors(tmp_path):
    with pytest.raises(ModelError, match="base.*rigid"):
        models.chain_from_dict({"name": "t", "dh": [{"a": 1, "alpha": 0, "d": 0, "theta": 0}],
                                "base": [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]})
    with pytest.raises(ModelError, match=r"tool\.xyz"):
        models.chain_from_dict({"name": "t", "dh": [{"a": 1, "alpha": 0, "d": 0, "theta": 0}],
                                "tool": {"xyz": [0, 0]}})
    with pytest.raises(ModelError, match="dh: expected a non-empty list"):
        models.chain_from_dict({"name": "t", "dh": []})
    with pytest.raises(ModelError, match="not found"):
        load(tmp_path / "missing.yaml")
    with pytest.raises(ModelError, match="top level"):
        models.chain_from_dict([1, 2])


# ----------------------------------------------------------------------------------- workspace
def test_sample_workspace_planar_and_anthropomorphic():
    planar = load("three_link_planar", dtype=F64)
    g = torch.Generator().manual_seed(0)
    p, q = models.sample_workspace(planar, 5000, generator=g, return_q=True)
    assert p.shape == (5000, 3) and q.shape == (5000, 3) and not p.requires_grad
    assert p[:, 2].abs().max() == 0 and p[:, :2].norm(dim=-1).max() <= 1.5 + 1e-12
    assert p[:, :2].norm(dim=-1).max() > 1.3  # the sampling reaches near the boundary
    again = models.sample_workspace(planar, 5000, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(again, p)
    arm = load("anthropomorphic_arm")
    pa = models.sample_workspace(arm, 2000)
    assert pa.norm(dim=-1).max() <= 1.0 + 1e-5  # reach a2 + a3
    panda = load("panda")
    pp = models.sample_workspace(panda, 2000)
    assert pp.dtype == torch.float32 and (pp.norm(dim=-1) < 1.2).all()


@pytest.mark.parametrize("dtype", [torch.int64, torch.int32, torch.float16, torch.bfloat16, torch.bool])
def test_a_model_in_another_dtype_is_refused(dtype):
    """load("panda", dtype=torch.int64) used to return a float32 robot with its DH table truncated."""
    from diffkin.errors import DTypeError

    with pytest.raises(DTypeError, match="float32 or torch.float64"):
        load("panda", dtype=dtype)
    with pytest.raises(DTypeError):
        models.from_urdf(models.DATA_DIR.parent.parent.parent / "tests" / "data" / "urdf" / "ur10.urdf",
                         "tool0", dtype=dtype)
    assert load("panda", dtype=torch.float64).dh_table().dtype == torch.float64


@pytest.mark.parametrize("value", ["nan 0 0", "0 inf 0", "0 0 -inf"])
def test_a_urdf_with_non_finite_origin_is_refused(value):
    import re
    from pathlib import Path

    text = (Path(__file__).parent / "data" / "urdf" / "ur10.urdf").read_text()
    bad = re.sub(r'(<joint name="shoulder_lift_joint".*?<origin[^>]*?xyz=")[^"]*', rf"\g<1>{value}", text,
                 count=1, flags=re.S)
    assert bad != text
    with pytest.raises(ModelError, match="shoulder_lift_joint"):
        models.from_urdf(bad, "tool0")

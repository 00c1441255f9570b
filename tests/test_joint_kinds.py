"""A new joint kind built from the existing motions is one row of ``JOINT_KINDS``: registered here, in the
test, a URDF using it loads and its FK, Jacobian, integrate and limits work, against an equivalent chain of
standard joints and closed forms (SciPy's rotations)."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from diffkin.kernels.configuration import JOINT_KINDS, MOTIONS, JointKind, joint_kind
from diffkin.models import from_urdf
from diffkin.models.urdf_xml import joint_types, moves
from diffkin.viz.joints import slider_specs


def _joint(name, jtype, parent, child, xyz="0 0 0", rpy="0 0 0", axis="0 0 1", limit=""):
    return (f'<joint name="{name}" type="{jtype}"><parent link="{parent}"/><child link="{child}"/>'
            f'<origin xyz="{xyz}" rpy="{rpy}"/><axis xyz="{axis}"/>{limit}</joint>')


def _robot(*joints):
    links = sorted(set(re.findall(r'link="(\w+)"', "".join(joints))))
    body = "".join(f'<link name="{n}"/>' for n in links) + "".join(joints)
    return f'<robot name="k">{body}</robot>'


@pytest.fixture
def new_kinds(monkeypatch):
    """Two kinds the library does not ship, each one row: a cylindrical joint (a slide along the axis, then
    a turn about it) and a ball on a slider (a ball, then a slide along the rotated axis)."""
    monkeypatch.setitem(JOINT_KINDS, "cylindrical", JointKind("cylindrical", ("P", "R"), True,
                                                              urdf="cylindrical"))
    monkeypatch.setitem(JOINT_KINDS, "ball_slider", JointKind("ball_slider", ("S", "P"), False,
                                                              urdf="ball_slider"))


_FIRST = _joint("j1", "revolute", "l0", "l1", "0.1 0 0.3", "0.2 0 0", "0 0 1",
                '<limit lower="-2" upper="2"/>')
_TOOL = _joint("tool", "fixed", "l2", "l3", "0.05 0.1 0.2", "0 0.3 0")


def test_a_cylindrical_kind_is_one_row(new_kinds):
    """The chain with the new kind equals the same chain written as a prismatic then a continuous joint on
    the same axis: FK, Jacobian, limits; q ⊕ v adds; the viewer labels its two sliders."""
    place, limit = ("0 0.4 0", "0 0.5 0.1", "0 0.6 0.8"), '<limit lower="-0.5" upper="0.7"/>'
    cyl = from_urdf(_robot(_FIRST, _joint("j2", "cylindrical", "l1", "l2", *place, limit), _TOOL), "l3",
                    dtype=torch.float64)
    std = from_urdf(_robot(_FIRST, _joint("j2a", "prismatic", "l1", "l4", *place, limit),
                           _joint("j2b", "continuous", "l4", "l2", axis="0 0.6 0.8"), _TOOL),
                    "l3", dtype=torch.float64)
    assert cyl.joint_kinds == ["revolute", "cylindrical"] and (cyl.nq, cyl.nv) == (3, 3)
    assert "cylindrical" in joint_types() and moves("cylindrical") and not moves("fixed")
    assert cyl.joint_types == std.joint_types == "RPR"
    q = torch.tensor([[0.3, 0.2, -1.1], [-1.0, -0.4, 2.5]], dtype=torch.float64)
    torch.testing.assert_close(cyl.forward_kinematics(q), std.forward_kinematics(q), rtol=0, atol=1e-12)
    torch.testing.assert_close(cyl.geometric_jacobian(q), std.geometric_jacobian(q), rtol=0, atol=1e-12)
    lo, hi = cyl.lower_upper()
    assert lo[:2].tolist() == [-2.0, -0.5] and hi[:2].tolist() == [2.0, 0.7]  # both coordinates limited
    v = torch.tensor([0.1, -0.2, 0.3], dtype=torch.float64)
    torch.testing.assert_close(cyl.integrate(q, v), q + v)
    labels = [s.label for s in slider_specs(cyl, lo.clamp_min(-3.0), hi.clamp_max(3.0))]
    assert labels == ["j1", "j2.z", "j2.theta"]


def test_a_kind_with_a_quaternion_is_one_row(new_kinds):
    """A ball then a slide along the rotated axis: nq 5, nv 4; FK the closed form O · A · R(quat) · Tz(d) ·
    Aᵀ · T_tool (SciPy's quaternion); the Jacobian the central difference of FK along q ⊕ εv; the
    quaternion stays unit under integrate and difference inverts it."""
    kind = joint_kind("ball_slider")
    assert (kind.nq, kind.nv, kind.has_axis) == (5, 4, True) and set(kind.letters) <= set(MOTIONS)
    axis = np.array([0.0, 0.6, 0.8])
    urdf = _robot(_joint("j2", "ball_slider", "l0", "l2", "0.1 0.2 0.3", "0.4 -0.2 0.1", "0 0.6 0.8"), _TOOL)
    chain = from_urdf(urdf, "l3", dtype=torch.float64)
    assert chain.joint_kinds == ["ball_slider"] and (chain.nq, chain.nv) == (5, 4)
    assert chain.configuration_space.motions == ("S", "P")
    g = torch.Generator().manual_seed(3)
    quat = torch.nn.functional.normalize(torch.randn(4, 4, generator=g, dtype=torch.float64), dim=-1)
    q = torch.cat((quat, 0.5 * torch.randn(4, 1, generator=g, dtype=torch.float64)), dim=-1)

    def tf(R=None, p=(0.0, 0.0, 0.0)):
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = np.eye(3) if R is None else R, p
        return T

    # e_z onto the axis (any such rotation: the ball and the slide are invariant to the choice about it,
    # since A and Aᵀ enclose them)
    A = tf(Rotation.align_vectors([axis], [[0.0, 0.0, 1.0]])[0].as_matrix())
    O = tf(Rotation.from_euler("xyz", [0.4, -0.2, 0.1]).as_matrix(), (0.1, 0.2, 0.3))
    tool = tf(Rotation.from_euler("xyz", [0.0, 0.3, 0.0]).as_matrix(), (0.05, 0.1, 0.2))
    ref = np.stack([O @ A @ tf(Rotation.from_quat(np.roll(x[:4], -1)).as_matrix()) @ tf(p=(0, 0, x[4]))
                    @ A.T @ tool for x in q.numpy()])
    np.testing.assert_allclose(chain.forward_kinematics(q).numpy(), ref, atol=1e-12)

    J = chain.geometric_jacobian(q)  # (4, 6, 4)
    eps = 1e-6
    for k in range(4):
        v = torch.zeros(4, dtype=torch.float64)
        v[k] = eps
        Tp, Tm = (chain.forward_kinematics(chain.integrate(q, s * v)) for s in (1.0, -1.0))
        lin = (Tp[:, :3, 3] - Tm[:, :3, 3]) / (2 * eps)
        rel = (Tp[:, :3, :3] @ Tm[:, :3, :3].transpose(-1, -2)).numpy()
        ang = torch.from_numpy(Rotation.from_matrix(rel).as_rotvec()) / (2 * eps)
        torch.testing.assert_close(J[:, :3, k], lin, atol=1e-7, rtol=0)
        torch.testing.assert_close(J[:, 3:, k], ang, atol=1e-7, rtol=0)

    v = torch.tensor([0.3, -2.0, 1.0, 0.25], dtype=torch.float64)
    q1 = chain.integrate(q, v)
    torch.testing.assert_close(q1[:, :4].norm(dim=-1), torch.ones(4, dtype=torch.float64))
    torch.testing.assert_close(chain.difference(q, q1), v.expand(4, 4))
    assert chain.q_limits.isinf().all()  # an unlimited kind: no limits from the file


def test_a_kind_of_an_unknown_motion_is_refused():
    with pytest.raises(ValueError, match="motion"):
        JointKind("twist", ("Q",), False)
    with pytest.raises(ValueError, match="axis"):
        JointKind("tilted_ball", ("Sx",), False)
    assert math.isinf(joint_kind("continuous").limits(-1.0, 1.0)[0][0])  # an unlimited kind drops them

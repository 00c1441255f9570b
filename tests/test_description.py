"""The format-neutral tree description: a hand-written one against the textbook's closed form, and the URDF
and MJCF readers producing the topology their chains run on."""

import math
from pathlib import Path

import pytest
import torch

from diffkin.errors import ModelError
from diffkin.kernels.joints import origin_transform
from diffkin.models import from_mjcf, from_urdf
from diffkin.models.description import FrameSpec, TreeChain, TreeDescription

F64 = torch.float64
DATA = Path(__file__).parent / "data"


class PlanarArm(TreeChain):
    """Two revolute joints about z, links of learnable length along x: the two-link planar arm."""

    def __init__(self, lengths):
        frames = [FrameSpec("R", -1, (), (("L", 0),), 0), FrameSpec("R", 0, (), (("L", 1),), 1)]
        desc = TreeDescription("planar2", frames, [1], [[]], 2, [[-math.pi, math.pi]] * 2, ["j1", "j2"],
                               ["revolute", "revolute"],
                               parameters={"length": torch.tensor(lengths, dtype=F64)})
        super().__init__(desc, dtype=F64)

    def _factors(self, eye):
        zero = torch.zeros_like(self.length)
        xyz = torch.stack((self.length, zero, zero), dim=-1)
        return {"L": origin_transform(xyz, torch.zeros_like(xyz)).unbind(0)}


def test_hand_written_description_matches_the_planar_arm_closed_form():
    arm = PlanarArm([0.7, 0.4]).requires_grad_()  # learnable on request
    q = torch.rand(64, 2, dtype=F64) * 6 - 3
    T = arm.forward_kinematics(q)
    c1, c12 = torch.cos(q[:, 0]), torch.cos(q.sum(-1))
    s1, s12 = torch.sin(q[:, 0]), torch.sin(q.sum(-1))
    torch.testing.assert_close(T[:, 0, 3], 0.7 * c1 + 0.4 * c12, rtol=0, atol=1e-12)
    torch.testing.assert_close(T[:, 1, 3], 0.7 * s1 + 0.4 * s12, rtol=0, atol=1e-12)
    # the lengths are learnable: d x / d a = (cos q1, cos(q1 + q2)) summed over the batch
    T[:, 0, 3].sum().backward()
    torch.testing.assert_close(arm.length.grad, torch.stack((c1.sum(), c12.sum())), rtol=0, atol=1e-10)


def test_frame_spec_refuses_an_unknown_motion():
    with pytest.raises(ModelError, match="motion"):
        FrameSpec("Q", -1)


def test_readers_produce_the_topology_their_chains_run_on():
    chain = from_urdf(DATA / "urdf" / "fr3.urdf", "fr3_link8")
    assert chain.description.topology() == chain.topology
    assert chain.description.joint_names == chain.joint_names
    assert [f.motion for f in chain.description.frames] == ["R"] * 7
    g1 = from_mjcf(DATA / "mjcf" / "unitree_g1" / "g1.xml", ["left_ankle_roll_link", "right_ankle_roll_link"])
    d = g1.description
    assert d.topology() == g1.topology and d.nq == g1.nq
    assert [f.motion for f in d.frames][:4] == ["P", "P", "P", "S"]  # the floating base

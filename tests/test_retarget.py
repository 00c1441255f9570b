"""diffkin.retarget (issue 37): the clip loaders on the shipped CMU files, the Motion checks, the foot soles
against MuJoCo, the artefact metrics against hand-computed values, the built-in G1 mapping and contacts."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest
import torch

from diffkin import models, retarget
from diffkin.errors import ConventionError, ModelError, NonFiniteError, OptionError, ShapeError
from diffkin.retarget.bvh import CMU_UNIT
from diffkin.retarget.mapping import SKELETONS

mujoco = pytest.importorskip("mujoco")
Rotation = pytest.importorskip("scipy.spatial.transform").Rotation

DATA = Path(__file__).parent / "data"
G1_URDF = DATA / "urdf" / "g1_29dof_rev_1_0.urdf"
G1_OLD = DATA / "mjcf" / "unitree_g1" / "g1.xml"
C = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # y up -> z up


def _offsets(path: Path) -> list[list[float]]:
    """The OFFSET rows of a BVH file in order (joints and End Sites), read independently of the loader."""
    head = path.read_text().split("MOTION")[0]
    return [[float(v) for v in m.split()] for m in re.findall(r"OFFSET\s+([-\d.\s]+?)\s*\n", head)]


# ------------------------------------------------------------------------------------------ loaders
@pytest.mark.parametrize("name, frames, fps", [("walk", 150, 60), ("crouch", 120, 60), ("hop", 120, 60),
                                               ("turn", 110, 60), ("reach", 74, 60), ("walkturn", 63, 30),
                                               ("pickup", 54, 30), ("squat", 69, 30)])
def test_shipped_clips_load(name, frames, fps):
    path = retarget.example_clips()[name]
    m = retarget.load_bvh(path)
    assert (m.batch, m.frames, len(m.names)) == (1, frames, 38)  # 31 joints + 7 End Sites
    assert m.fps == fps
    human = SKELETONS[retarget.skeleton_of(m.names)]
    assert m.orientations.shape == (1, frames, 38, 3, 3)
    # bone lengths: constant over frames and equal to the file's offsets in CMU units
    off = np.array(_offsets(path))
    p = m.positions[0].numpy()
    for j, parent in enumerate(m.parents):
        if parent < 0:
            continue
        length = np.linalg.norm(p[:, j] - p[:, parent], axis=-1)
        np.testing.assert_allclose(length, np.linalg.norm(off[j]) * CMU_UNIT, atol=1e-9)
    # standing on the floor: the lowest foot point of every frame is within a few cm of z = 0
    ends = (("toe", ""), ("toe", "_end"), ("ankle", ""))
    feet = m.index([human[f"{s}_{j}"] + e for s in ("left", "right") for j, e in ends])
    lowest = p[:, feet, 2].min(-1)
    assert np.all(lowest > -0.03) and np.median(lowest) < 0.08
    # an adult: pelvis 0.8-1.1 m high in the first frame, head top above 1.3 m
    assert 0.8 < p[0, m.index("Hips")[0], 2] < 1.1
    assert p[0, m.index("Head_end")[0], 2] > 1.3


def test_shipped_turn_and_reach_are_what_they_say():
    """The turn turns the pelvis (hip line) > 110° to the left and back within 15°; the reach takes the right
    wrist from below the shoulder to 20 cm above it with the elbow straightened (shoulder-wrist distance
    > 95 % of the arm's length, from < 60 %) while the pelvis stays within 5 cm."""
    turn = retarget.load_bvh(retarget.example_clips()["turn"])
    p = turn.positions[0].numpy()
    d = p[:, turn.index("LeftHip")[0]] - p[:, turn.index("RightHip")[0]]
    yaw = np.degrees(np.unwrap(np.arctan2(d[:, 1], d[:, 0])))
    assert yaw.max() - yaw[0] > 110 and abs(yaw[-1] - yaw[0]) < 15
    reach = retarget.load_bvh(retarget.example_clips()["reach"])
    s, e, w, h = (reach.joint(n)[0].numpy() for n in ("RightShoulder", "RightElbow", "RightWrist", "Hips"))
    arm = np.linalg.norm(e - s, axis=-1) + np.linalg.norm(w - e, axis=-1)
    straight = np.linalg.norm(w - s, axis=-1) / arm
    assert w[0, 2] < s[0, 2] and w[-1, 2] > s[-1, 2] + 0.2
    assert straight[0] < 0.6 and straight[-1] > 0.95
    assert np.linalg.norm(h - h[0], axis=-1).max() < 0.05


def test_shipped_walkturn_and_pickup_are_what_they_say():
    """The walk with a turn walks > 1 m before and > 20 cm after turning the hip line by 75-95° to the left;
    the pick-up takes the left wrist from above 0.6 m to below 0.3 m above the floor and back above 0.5 m,
    the pelvis down by > 10 cm, after walking > 1 m. Both are the MotionBuilder-named CMU skeleton."""
    walk = retarget.load_bvh(retarget.example_clips()["walkturn"])
    assert retarget.skeleton_of(walk.names) == "cmu_mb"
    p = walk.positions[0].numpy()
    d = p[:, walk.index("LeftUpLeg")[0]] - p[:, walk.index("RightUpLeg")[0]]
    yaw = np.degrees(np.unwrap(np.arctan2(d[:, 1], d[:, 0])))
    hips = p[:, walk.index("Hips")[0], :2]
    turning = np.nonzero(np.abs(yaw - yaw[0]) > 10)[0][0]
    assert 75 < yaw[-1] - yaw[0] < 95
    assert np.linalg.norm(hips[turning] - hips[0]) > 1.0 and np.linalg.norm(hips[-1] - hips[-8]) > 0.2
    pick = retarget.load_bvh(retarget.example_clips()["pickup"])
    q = pick.positions[0].numpy()
    wrist, pelvis = q[:, pick.index("LeftHand")[0], 2], q[:, pick.index("Hips")[0]]
    low = wrist.argmin()
    assert wrist[0] > 0.6 and wrist[low] < 0.3 and wrist[-1] > 0.5
    assert pelvis[0, 2] - pelvis[low, 2] > 0.1
    assert np.linalg.norm(pelvis[low, :2] - pelvis[0, :2]) > 1.0
    with pytest.raises(ConventionError, match="cmu_mb"):
        retarget.skeleton_of(["Hips", "Spine"])


def test_shipped_squat_is_what_it_says():
    """The squat (MotionBuilder-named skeleton) takes the pelvis from standing (> 0.95 m) down by > 0.5 m and
    back up to within 3 cm of its start, both knees bent by 150° at the bottom (thigh-shank angle < 30°,
    from > 150° standing), the pelvis within 12 cm of its start horizontally and each ankle within 12 cm of
    its start: a squat in place, not a step; and the MOTION rows are the README's every-4th-row selection
    (30 fps, 69 frames) with the HIERARCHY's 38 OFFSET rows."""
    path = retarget.example_clips()["squat"]
    m = retarget.load_bvh(path)
    assert retarget.skeleton_of(m.names) == "cmu_mb" and (m.frames, m.fps) == (69, 30)
    assert len(_offsets(path)) == 38
    p = m.positions[0].numpy()
    hips = p[:, m.index("Hips")[0]]
    low = hips[:, 2].argmin()
    assert hips[0, 2] > 0.95 and hips[0, 2] - hips[low, 2] > 0.5 and abs(hips[-1, 2] - hips[0, 2]) < 0.03
    assert 0 < low < m.frames - 1
    assert np.linalg.norm(hips[:, :2] - hips[0, :2], axis=-1).max() < 0.12
    for side in ("Left", "Right"):
        hip, knee, ankle = (p[:, m.index(f"{side}{j}")[0]] for j in ("UpLeg", "Leg", "Foot"))
        u, v = hip - knee, ankle - knee
        cos = (u * v).sum(-1) / (np.linalg.norm(u, axis=-1) * np.linalg.norm(v, axis=-1))
        angle = np.degrees(np.arccos(cos))
        assert angle[0] > 150 and angle[low] < 30
        assert np.linalg.norm(ankle[:, :2] - ankle[0, :2], axis=-1).max() < 0.12


def test_bvh_root_against_scipy():
    """The root's frame and position against scipy's intrinsic Euler composition (channels Z Y X)."""
    path = retarget.example_clips()["walk"]
    rows = path.read_text().split("MOTION")[1].strip().splitlines()[2:]
    m = retarget.load_bvh(path)
    for t in (0, 77, 149):
        v = [float(x) for x in rows[t].split()]
        R = Rotation.from_euler("ZYX", v[3:6], degrees=True).as_matrix()
        np.testing.assert_allclose(m.orientations[0, t, 0].numpy(), C @ R, atol=1e-12)
        np.testing.assert_allclose(m.positions[0, t, 0].numpy(), C @ np.array(v[:3]) * CMU_UNIT, atol=1e-12)
        # a child: LeftHipJoint (offset 0) then LeftHip at R_root R_lhj offset
        lhj = Rotation.from_euler("ZYX", v[6:9], degrees=True).as_matrix()
        off = np.array(_offsets(path)[2]) * CMU_UNIT
        want = C @ (np.array(v[:3]) * CMU_UNIT + R @ lhj @ off)
        np.testing.assert_allclose(m.joint("LeftHip")[0, t].numpy(), want, atol=1e-12)


def test_bvh_scale_and_errors(tmp_path):
    path = retarget.example_clips()["hop"]
    m = retarget.load_bvh(path, scale=1.0)  # file units
    ref = retarget.load_bvh(path)
    torch.testing.assert_close(m.positions * CMU_UNIT, ref.positions, atol=1e-12, rtol=0)
    with pytest.raises(ModelError, match="not found"):
        retarget.load_bvh(tmp_path / "none.bvh")
    bad = tmp_path / "bad.bvh"
    text = path.read_text()
    bad.write_text(text.replace("Frames: 120", "Frames: 121"))
    with pytest.raises(ModelError, match="121 frames"):
        retarget.load_bvh(bad)
    bad.write_text(text.replace("Zrotation", "Wrotation", 1))
    with pytest.raises(ModelError, match="unknown channel"):
        retarget.load_bvh(bad)
    with pytest.raises(OptionError, match="scale"):
        retarget.load_bvh(path, scale=-1.0)


def test_load_smpl(tmp_path):
    rng = np.random.default_rng(0)
    joints = rng.normal(size=(5, 24, 3))
    np.savez(tmp_path / "a.npz", joints=joints, mocap_framerate=30.0)
    m = retarget.load_smpl(tmp_path / "a.npz")
    assert m.names == retarget.SMPL_JOINT_NAMES and m.fps == 30.0 and m.positions.shape == (1, 5, 24, 3)
    np.testing.assert_allclose(m.positions[0].numpy(), joints)
    y = retarget.load_smpl(tmp_path / "a.npz", up="y")
    np.testing.assert_allclose(y.positions[0].numpy(), joints @ C.T)
    np.savez(tmp_path / "x.npz", joints=rng.normal(size=(2, 4, 55, 3)), fps=np.array(120))
    assert retarget.load_smpl(tmp_path / "x.npz").names == retarget.SMPLX_JOINT_NAMES
    np.savez(tmp_path / "b.npz", poses=joints)
    with pytest.raises(ModelError, match="no array 'joints'"):
        retarget.load_smpl(tmp_path / "b.npz", fps=30)
    np.savez(tmp_path / "c.npz", joints=rng.normal(size=(5, 17, 3)))
    with pytest.raises(ModelError, match="17 joints"):
        retarget.load_smpl(tmp_path / "c.npz", fps=30)
    with pytest.raises(ModelError, match="frame rate"):
        retarget.load_smpl(tmp_path / "c.npz", names=[f"j{i}" for i in range(17)])


def test_motion_checks():
    p = torch.zeros(2, 4, 3, 3)
    m = retarget.Motion(p, ["a", "b", "c"], 30)
    assert (m.batch, m.frames) == (2, 4) and m.duration == pytest.approx(0.1)
    bad = p.clone()
    bad[1, 2, 0, 1] = float("nan")
    with pytest.raises(NonFiniteError, match=r"clip 1, frame 2"):
        retarget.Motion(bad, ["a", "b", "c"], 30)
    for fps in (0, -5.0, float("nan")):
        with pytest.raises((OptionError, NonFiniteError), match="fps"):
            retarget.Motion(p, ["a", "b", "c"], fps)
    with pytest.raises(ShapeError, match="3 joint names"):
        retarget.Motion(p, ["a", "b"], 30)
    with pytest.raises(ShapeError, match="positions"):
        retarget.Motion(torch.zeros(2, 4, 3, 2), ["a", "b", "c"], 30)
    with pytest.raises(ShapeError, match="orientations"):
        retarget.Motion(p, ["a", "b", "c"], 30, orientations=torch.zeros(2, 4, 3, 3))
    with pytest.raises(ModelError, match="unique"):
        retarget.Motion(p, ["a", "a", "c"], 30)
    with pytest.raises(ModelError, match=r"\['zz'\]"):
        m.index(["a", "zz"])


# ------------------------------------------------------------------------------------- soles, metrics
def test_sole_against_mujoco():
    """The G1's lowest foot point from the sole read off its geoms, against MuJoCo's placed foot geoms."""
    from diffkin.models.mjcf import compile_mjcf

    feet = ["left_ankle_roll_link", "right_ankle_roll_link"]
    chain = models.from_mjcf(G1_OLD, feet, dtype=torch.float64)
    model = compile_mjcf(G1_OLD)[0]
    data = mujoco.MjData(model)
    g = torch.Generator().manual_seed(3)
    for _ in range(4):
        qpos = model.qpos0.copy()
        qpos[7:] += torch.empty(model.nq - 7).uniform_(-0.3, 0.3, generator=g).numpy()
        qpos[3:7] = Rotation.from_rotvec(torch.empty(3).uniform_(-0.4, 0.4, generator=g).numpy()).as_quat(
            scalar_first=True)
        data.qpos[:] = qpos
        mujoco.mj_kinematics(model, data)
        with torch.no_grad():
            T = chain.forward_kinematics(chain.from_qpos(torch.as_tensor(qpos)))
        for k, foot in enumerate(feet):
            bid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, foot)
            gs = [i for i in range(model.ngeom) if model.geom_bodyid[i] == bid and model.geom_contype[i]
                  and model.geom_type[i] == mujoco.mjtGeom.mjGEOM_SPHERE and model.geom_size[i, 0] < 0.005]
            assert len(gs) == 4
            want = min(data.geom_xpos[i, 2] - model.geom_size[i, 0] for i in gs)
            height, centre = retarget.sole_of(chain, foot).lowest(T[k])
            assert float(height) == pytest.approx(want, abs=1e-12)
            np.testing.assert_allclose(centre.numpy(), data.geom_xpos[gs].mean(0), atol=1e-12)


def test_sole_of_urdf_g1():
    chain = models.from_urdf(G1_URDF, ["left_ankle_roll_link", "right_ankle_roll_link"], floating_base=True)
    s = retarget.sole_of(chain, "left_ankle_roll_link")
    np.testing.assert_allclose(s.points.numpy(), [[-0.05, 0.025, -0.03], [-0.05, -0.025, -0.03],
                                                   [0.12, 0.03, -0.03], [0.12, -0.03, -0.03]])
    np.testing.assert_allclose(s.radii.numpy(), [0.005] * 4)


FEET_XML = """
<mujoco>
  <compiler angle="radian"/>
  <worldbody>
    <body name="lfoot"><freejoint/>
      <geom type="box" size="0.1 0.05 0.02" pos="0 0 -0.03"/>
      <geom type="sphere" size="0.5" contype="0" conaffinity="0"/>
    </body>
    <body name="rfoot"><freejoint/>
      <geom type="sphere" size="0.01" pos="0.05 0 -0.02"/>
      <geom type="sphere" size="0.01" pos="-0.05 0 -0.02"/>
    </body>
    <body name="arm" pos="0 0 1"><joint name="hinge" axis="0 0 1" range="-1 1"/>
      <geom type="capsule" size="0.02 0.1"/>
    </body>
  </worldbody>
</mujoco>
"""


def _close(x, want):
    torch.testing.assert_close(x, torch.tensor(want, dtype=torch.float64), atol=1e-5, rtol=0)  # mm


def test_metrics_hand_computed():
    """A constructed clip of two free feet and a limited hinge, 6 frames at 10 fps, every metric by hand."""
    chain = models.from_mjcf(FEET_XML, ["lfoot", "rfoot", "arm"], dtype=torch.float64)
    assert chain.joint_kinds == ["free", "free", "revolute"]
    T, fps = 6, 10.0
    q = torch.zeros(2, T, 15, dtype=torch.float64)
    q[..., 3] = q[..., 10] = 1.0  # identity quaternions
    # left foot: box bottom 0.05 below the body origin; right: spheres 0.03 below
    q[0, :, 0] = torch.tensor([0.0, 0.01, 0.03, 0.03, 0.5, 0.5])
    q[0, :, 2] = torch.tensor([0.05, 0.05, 0.045, 0.06, 0.2, 0.05])  # heights 0, 0, -5 mm, 10 mm, 150 mm, 0
    q[0, :, 8] = torch.tensor([0.0, 0.0, 0.004, 0.004, 0.004, 0.01])
    q[0, :, 9] = 0.04  # right sole 10 mm above the ground throughout
    q[0, :, 14] = torch.tensor([0.0, 0.5, 1.2, 1.0, -1.5, 0.0])  # beyond the limits at 1.2 and -1.5
    q[1] = q[0]
    q[1, :, 14] = 0.0
    contacts = torch.zeros(2, T, 2, dtype=torch.bool)
    contacts[0, :, 0] = torch.tensor([1, 1, 1, 1, 0, 1], dtype=torch.bool)
    contacts[0, :, 1] = torch.tensor([0, 1, 1, 0, 1, 1], dtype=torch.bool)
    targets = torch.zeros(2, T, 1, 3, dtype=torch.float64)
    targets[..., 2] = 1.003
    m = retarget.metrics(chain, q, contacts, fps, feet=("lfoot", "rfoot"), keypoints=targets,
                         keypoint_frames=["arm"])
    # phases: left frames 0-3 (10 + 20 + 0 mm) and 5 (0); right 1-2 (4 mm) and 4-5 (6 mm): median (4+6)/2
    torch.testing.assert_close(m.contact_phases, torch.tensor([4, 0]))
    _close(m.foot_skating, [5.0, 0.0])
    _close(m.ground_penetration, [5.0, 5.0])
    # contact frames: left 0, 0, 0 (below counts 0), 10, 0 mm; right 10 mm x 4 -> 50 mm / 9
    _close(m.floating, [50.0 / 9, 0.0])
    torch.testing.assert_close(m.joint_limit_violations, torch.tensor([2, 0]))
    _close(m.joint_limit_excess, [0.5, 0.0])
    _close(m.max_joint_velocity, [25.0, 0.0])
    _close(m.keypoint_error, [3.0, 3.0])
    assert set(m.as_dict()) >= {"foot_skating", "floating", "ground_penetration", "joint_limit_violations"}
    # an odd number of phases: the middle one; the ground raised by 10 mm: penetration grows by 10 mm
    c1 = contacts[:1].clone()
    c1[0, 5, 0] = False
    m1 = retarget.metrics(chain, q[:1], c1, fps, feet=("lfoot", "rfoot"), ground=0.01)
    _close(m1.foot_skating, [6.0])
    _close(m1.ground_penetration, [15.0])


def test_metrics_errors():
    chain = models.from_mjcf(FEET_XML, ["lfoot", "rfoot", "arm"], dtype=torch.float64)
    q = torch.zeros(1, 3, 15, dtype=torch.float64)
    c = torch.zeros(1, 3, 2, dtype=torch.bool)
    with pytest.raises(ModelError, match="feet"):
        retarget.metrics(chain, q, c, 30, feet=("lfoot", "nofoot"))
    with pytest.raises(ShapeError, match="contacts"):
        retarget.metrics(chain, q, c[:, :2], 30, feet=("lfoot", "rfoot"))
    with pytest.raises(OptionError, match="fps"):
        retarget.metrics(chain, q, c, 0, feet=("lfoot", "rfoot"))
    bad = q.clone()
    bad[0, 1, 0] = float("nan")
    with pytest.raises(NonFiniteError, match="q"):
        retarget.metrics(chain, bad, c, 30, feet=("lfoot", "rfoot"))
    with pytest.raises(ModelError, match="neither a body nor a site|not among|feet"):
        retarget.metrics(chain, q, c, 30, feet=("lfoot", "hinge"))
    # a capsule sole: the arm's capsule (half length 0.1, radius 0.02) at z = 1: lowest point 0.88 m
    q[..., 3] = q[..., 10] = 1.0
    m = retarget.metrics(chain, q, torch.ones_like(c), 30, feet=("lfoot", "arm"))
    _close(m.floating, [880.0 / 2])


# ------------------------------------------------------------------------------------ mapping, contacts
def test_builtin_g1_mapping_on_the_29dof_model():
    mp = retarget.Mapping.builtin("g1")
    assert mp.frames[:2] == ["left_ankle_roll_link", "right_ankle_roll_link"]
    chain = models.from_urdf(G1_URDF, mp.frames, floating_base=True)  # every frame is a body of the model
    assert chain.end_links == mp.frames and chain.nq == 7 + 29  # the free base and all 29 hinges
    clip = retarget.load_bvh(retarget.example_clips()["walk"])
    mp.check(clip)
    x = mp.targets(clip)
    assert x.shape == (1, 150, len(mp.keypoint_frames), 3)
    torch.testing.assert_close(x[0, :, 0], clip.joint("LeftAnkle")[0])
    # metrics run on the mapping's chain (a standing G1 at its reference height)
    q = torch.zeros(1, 2, chain.nq, dtype=chain.dtype)
    q[..., 2], q[..., 3] = 0.793, 1.0
    m = retarget.metrics(chain, q, torch.ones(1, 2, 2, dtype=torch.bool), 30, feet=mp.feet)
    assert m.joint_limit_violations.item() == 0 and m.max_joint_velocity.item() == 0.0


def test_mapping_errors():
    clip = retarget.load_bvh(retarget.example_clips()["walk"])
    mp = retarget.Mapping({"left_ankle_roll_link": "LeftAnkle", "right_ankle_roll_link": "RightAnkle",
                           "pelvis": "Pelvis"}, feet=("left_ankle_roll_link", "right_ankle_roll_link"))
    with pytest.raises(ModelError, match="'Pelvis'"):
        mp.check(clip)
    with pytest.raises(ModelError, match="feet"):
        retarget.Mapping({"a": "b"}, feet=("a", "a"))
    with pytest.raises(ModelError, match="weights"):
        retarget.Mapping({"a": "b", "c": "d"}, feet=("a", "c"), weights={"zz": 1.0})
    with pytest.raises(ConventionError, match="no built-in"):
        retarget.Mapping.builtin("nao")
    mp2 = retarget.Mapping({"a": "LeftAnkle", "c": "RightAnkle", "p": "Hips"}, feet=("a", "c"),
                           weights={"p": (2.0, 0.5)}, offsets={"p": (0, 0, 0.1)})
    torch.testing.assert_close(mp2.weights[2], torch.tensor([2.0, 0.5], dtype=torch.float64))
    torch.testing.assert_close(mp2.targets(clip, scale=0.5)[0, :, 2],
                               0.5 * clip.joint("Hips")[0] + torch.tensor([0, 0, 0.1], dtype=torch.float64))


def test_contacts_of_the_walk():
    clip = retarget.load_bvh(retarget.example_clips()["walk"])
    c = retarget.Mapping.builtin("g1").contacts(clip)[0]
    assert c.shape == (150, 2)
    assert c.any(-1).float().mean() > 0.9  # walking: a foot on the ground almost always
    assert (~c).any(0).all() and c.any(0).all()  # each foot both swings and stands
    # a swinging foot moves: the ankle's mean horizontal speed off contact is several times that in contact
    for side, k in (("Left", 0), ("Right", 1)):
        ankle = clip.joint(f"{side}Ankle")[0, :, :2]
        v = (ankle[1:] - ankle[:-1]).norm(dim=-1) * clip.fps
        stance = c[1:, k] & c[:-1, k]
        assert v[~c[1:, k]].mean() > 3 * v[stance].mean() and v[~c[1:, k]].max() > 1.0
    none = retarget.detect_contacts(clip, ("LeftToe", "RightToe"), height=1e-3)
    assert not none.any()
    with pytest.raises(OptionError, match="speed"):
        retarget.detect_contacts(clip, ("LeftToe", "RightToe"), speed=0)


# ------------------------------------------------------------------------------------------- clip
def test_clip_round_trip_of_a_robot_clip(tmp_path):
    """A G1 clip made by diffkin's FK (feet planted, arms moving) mapped back through retarget.clip: the
    keypoints and the elbow motion are recovered and the feet do not skate."""
    clip = retarget.clip

    mp0 = retarget.Mapping.builtin("g1")
    g1 = models.from_urdf(G1_URDF, mp0.frames, floating_base=True, dtype=torch.float64)
    T = 20
    q = torch.zeros(T, g1.nq, dtype=torch.float64)
    q[:, 2], q[:, 3] = 0.793, 1.0
    names = g1.joint_names
    col = {n: 7 + i for i, n in enumerate(names[1:])}  # free joint first, then one column per hinge
    s = torch.linspace(0, 1, T, dtype=torch.float64)
    q[:, col["left_elbow_joint"]] = 0.3 + 0.8 * s
    q[:, col["right_elbow_joint"]] = 1.0 - 0.6 * s
    q[:, col["left_shoulder_pitch_joint"]] = -0.5 * s
    with torch.no_grad():
        P = g1.forward_kinematics(q)[..., :3, 3]  # (T, K, 3)
    motion = retarget.Motion(P, mp0.frames, 30.0)
    identity = retarget.Mapping({f: f for f in mp0.frames}, feet=mp0.feet)
    r = clip(g1, motion, identity, scale=1.0)
    assert r.q.shape == (1, T, g1.nq) and r.contacts.all()
    assert r.metrics.keypoint_error.item() < 1.0  # mm
    assert r.metrics.foot_skating.item() < 1.0 and r.metrics.ground_penetration.item() == 0.0
    assert int(r.metrics.joint_limit_violations) == 0
    # position targets leave the wrist's small link offsets redundant with the elbow: recovered to 0.05 rad
    for j in ("left_elbow_joint", "right_elbow_joint"):
        torch.testing.assert_close(r.q[0, :, col[j]], q[:, col[j]], atol=5e-2, rtol=0)
    # MuJoCo-free reference: the reported keypoint error is the FK distance to the targets
    with torch.no_grad():
        fk = g1.forward_kinematics(r.q[0])[..., :3, 3]
    assert float((fk - P).norm(dim=-1).mean() * 1000) == pytest.approx(r.metrics.keypoint_error.item())
    out = np.load(r.save(tmp_path / "clip.npz"))
    assert out["q"].shape == (1, T, g1.nq) and out["qd"].shape == (1, T, 29)
    assert float(out["fps"]) == 30.0 and len(out["joint_names"]) == 29
    np.testing.assert_allclose((out["root_quat"][0] ** 2).sum(-1), 1.0)


def test_clip_of_the_shipped_walk_runs_and_is_scored():
    clip, fit_scale = retarget.clip, retarget.fit_scale

    mp = retarget.Mapping.builtin("g1")
    g1 = models.from_urdf(G1_URDF, mp.frames, floating_base=True, dtype=torch.float64)
    walk = retarget.load_bvh(retarget.example_clips()["walk"]).frames_slice(0, 30)
    s = fit_scale(g1, walk, mp)
    assert 0.7 < float(s) < 1.0  # the G1 (1.3 m) is smaller than the CMU subject
    r = clip(g1, walk, mp)
    torch.testing.assert_close(r.scale, s)
    assert r.q.shape == (1, 30, g1.nq) and torch.isfinite(r.q).all()
    assert int(r.metrics.joint_limit_violations) == 0  # ik.solve respects the limits
    assert r.metrics.keypoint_error.item() < 100.0  # mm: a warm start, not yet the whole-clip optimisation
    with pytest.raises(ModelError, match="mapping's frames"):
        clip(models.from_urdf(G1_URDF, mp.frames[::-1], floating_base=True), walk, mp)


def test_h1_capsule_sole_against_mujoco():
    """The H1's feet are three capsules (``fromto``): the lowest sole point vs MuJoCo's placed capsules."""
    from diffkin.models.mjcf import compile_mjcf

    path = DATA / "mjcf" / "unitree_h1" / "h1.xml"
    mp = retarget.Mapping.builtin("h1")
    chain = models.from_mjcf(path, mp.frames, dtype=torch.float64)
    model = compile_mjcf(path)[0]
    data = mujoco.MjData(model)
    qpos = model.qpos0.copy()
    qpos[2] = 1.0
    qpos[3:7] = Rotation.from_rotvec([0.2, -0.3, 0.5]).as_quat(scalar_first=True)
    qpos[7:] += np.linspace(-0.3, 0.3, model.nq - 7)
    data.qpos[:] = qpos
    mujoco.mj_kinematics(model, data)
    with torch.no_grad():
        T = chain.forward_kinematics(chain.from_qpos(torch.as_tensor(qpos)))
    for k, foot in enumerate(mp.feet):
        bid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, foot)
        caps = [i for i in range(model.ngeom) if model.geom_bodyid[i] == bid
                and model.geom_type[i] == mujoco.mjtGeom.mjGEOM_CAPSULE and model.geom_contype[i]]
        assert len(caps) == 3
        ends = [data.geom_xpos[i] + sgn * model.geom_size[i, 1] * data.geom_xmat[i].reshape(3, 3)[:, 2]
                for i in caps for sgn in (-1, 1)]
        want = min(e[2] - model.geom_size[caps[0], 0] for e in ends)
        height, _ = retarget.sole_of(chain, foot).lowest(T[k])
        assert height.item() == pytest.approx(want, abs=1e-12)


def test_metrics_gradients_and_float32():
    """Penetration and floating are differentiable in q (finite differences, float64), and the metrics
    follow a float32 chain."""
    chain = models.from_mjcf(FEET_XML, ["lfoot", "rfoot", "arm"], dtype=torch.float64)
    q = torch.zeros(1, 3, 15, dtype=torch.float64)
    q[..., 3] = q[..., 10] = 1.0
    q[..., 4] = 0.1  # a tilted box: one lowest corner
    q[..., 2] = torch.tensor([0.02, 0.06, 0.07], dtype=torch.float64)
    q[..., 9] = 0.05
    c = torch.ones(1, 3, 2, dtype=torch.bool)

    def f(x):
        m = retarget.metrics(chain, x, c, 30, feet=("lfoot", "rfoot"))
        return torch.stack((m.ground_penetration, m.floating), -1)

    assert torch.autograd.gradcheck(f, (q.requires_grad_(),), eps=1e-7, atol=1e-5)
    chain32 = models.from_mjcf(FEET_XML, ["lfoot", "rfoot", "arm"], dtype=torch.float32)
    m32 = retarget.metrics(chain32, q.detach().float(), c, 30, feet=("lfoot", "rfoot"))
    m64 = retarget.metrics(chain, q.detach(), c, 30, feet=("lfoot", "rfoot"))
    assert m32.floating.dtype == torch.float32
    torch.testing.assert_close(m32.floating.double(), m64.floating, atol=1e-3, rtol=0)  # mm


# ------------------------------------------------------------------------------ whole-clip optimisation
def test_whole_clip_optimisation_on_the_shipped_hop():
    """Stage two on 20 frames of the shipped hop: every artefact metric within its bound and better than
    the frame-by-frame warm start's, the cost decreasing."""
    mp = retarget.Mapping.builtin("g1")
    g1 = models.from_urdf(G1_URDF, mp.frames, floating_base=True, dtype=torch.float64)
    hop = retarget.load_bvh(retarget.example_clips()["hop"]).frames_slice(0, 20)
    r = retarget.clip(g1, hop, mp, max_iterations=8, iterations=5)
    w, m = r.warm_start, r.metrics
    assert int(m.joint_limit_violations) == 0 and m.joint_limit_excess.item() == 0.0
    assert m.ground_penetration.item() <= 1.0  # mm
    assert m.floating.item() <= 5.0 < w.floating.item()  # the warm start floats (the scaled human ankle)
    assert m.foot_skating.item() <= min(5.0, w.foot_skating.item() / 3)
    assert m.keypoint_error.item() < 80.0
    assert m.max_joint_velocity.item() < 20.0  # rad/s, under the G1 motors' 20-37 rad/s
    assert r.cost.shape == (6, 1) and bool((r.cost[1:] <= r.cost[:-1]).all())
    assert r.cost[-1].item() < r.cost[0].item() / 10
    # the reported metrics are metrics() of the returned q
    again = retarget.metrics(g1, r.q, r.contacts, hop.fps, feet=mp.feet, keypoints=r.keypoints,
                             keypoint_frames=r.keypoint_frames)
    torch.testing.assert_close(again.foot_skating, m.foot_skating)
    # MuJoCo's FK of the output (the same URDF compiled by MuJoCo) gives the reported keypoint error
    model = _mujoco_g1()
    data = mujoco.MjData(model)
    adr = [0, 1, 2, 3, 4, 5, 6] + [int(model.joint(n).qposadr[0]) for n in g1.joint_names[1:]]
    ids = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, f) for f in r.keypoint_frames]
    feet = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, f) for f in mp.feet]
    soles = [g for g in range(model.ngeom) if model.geom_bodyid[g] in feet]  # the URDF's 4 + 4 foot spheres
    dist, lowest = [], []
    for t in range(r.q.shape[1]):
        data.qpos[adr] = r.q[0, t].numpy()
        mujoco.mj_kinematics(model, data)
        dist.append(np.linalg.norm(data.xpos[ids] - r.keypoints[0, t].numpy(), axis=-1))
        lowest.append(np.min(data.geom_xpos[soles, 2] - model.geom_size[soles, 0]))
    assert 1000 * np.mean(dist) == pytest.approx(m.keypoint_error.item(), abs=1e-6)
    # no sole point below the ground, exactly (the last step lifts the base): in MuJoCo's FK and the metric
    assert len(soles) == 8 and min(lowest) >= -1e-12
    assert m.ground_penetration.item() <= 1e-9  # mm


def _mujoco_g1():
    """The G1 URDF compiled by MuJoCo itself (meshes dropped, no body fused, a free joint on the pelvis)."""
    text = G1_URDF.read_text()
    text = re.sub(r"<visual>.*?</visual>", "", text, flags=re.S)
    text = re.sub(r"<collision>(?:(?!</collision>).)*<mesh[^>]*/>(?:(?!</collision>).)*</collision>", "",
                  text, flags=re.S)
    text = re.sub(r"(<robot [^>]*>)", r'\1<mujoco><compiler fusestatic="false"/></mujoco>', text, count=1)
    spec = mujoco.MjSpec.from_string(text)
    spec.worldbody.first_body().add_freejoint()
    return spec.compile()


def test_whole_clip_gradient_against_autograd():
    """The normal equations' right-hand side g = Jᵀr of the Gauss–Newton step is the gradient of the cost
    (autograd, pulled back to velocity coordinates): exactly with the difference terms off, on the
    hinge and base-position columns with them on (their base-rotation Jacobian is approximated)."""
    from diffkin.retarget.whole_clip import COSTS, _Terms, _velocity_limits
    from diffkin.rotations import _skew

    mp = retarget.Mapping.builtin("g1")
    g1 = models.from_urdf(G1_URDF, mp.frames, floating_base=True, dtype=torch.float64)
    B, T = 2, 5
    gen = torch.Generator().manual_seed(0)
    q = torch.zeros(B, T, g1.nq, dtype=torch.float64)
    q[..., 2], q[..., 3] = 0.78, 1.0
    q[..., 7:] = 0.2 * torch.randn(B, T, g1.nq - 7, generator=gen, dtype=torch.float64)
    q[..., 3:7] += 0.05 * torch.randn(B, T, 4, generator=gen, dtype=torch.float64)
    q[..., 3:7] /= q[..., 3:7].norm(dim=-1, keepdim=True)
    q[0, :, 7] = 2.9  # beyond the hip pitch's upper limit 2.8798: the limit term is active
    kp = mp.keypoint_frames
    with torch.no_grad():
        x = g1.forward_kinematics(q)[..., [g1.end_links.index(f) for f in kp], :3, 3]
    x = x + 0.03 * torch.randn(x.shape, generator=gen, dtype=torch.float64)
    contacts = torch.rand(B, T, 2, generator=gen) < 0.6
    q_ref = q + 0.01 * torch.randn(q.shape, generator=gen, dtype=torch.float64)
    q_ref[..., 3:7] /= q_ref[..., 3:7].norm(dim=-1, keepdim=True)
    cs = g1.configuration_space
    vmax = _velocity_limits(g1, 3.0, q)  # 0.1 rad per frame at 30 fps: active on many joints here
    off = {"velocity": 0.0, "acceleration": 0.0, "posture": 0.0}
    exact = [0, 1, 2, *range(6, g1.nv)]
    rv = 0.5 * torch.randn(B, T, len(kp), 3, generator=gen, dtype=torch.float64)
    R_d = torch.linalg.matrix_exp(_skew(rv))
    ow = torch.rand(len(kp), generator=gen, dtype=torch.float64) * (torch.arange(len(kp)) % 2)  # some 0
    cases = ((off, list(range(g1.nv)), None, None), ({}, exact, None, None), ({}, exact, vmax, None),
             (off, list(range(g1.nv)), None, R_d))
    for costs, cols, vel, ori in cases:
        w = {**COSTS, **costs}
        terms = _Terms(g1, x, contacts, list(mp.feet), kp, 30.0, 0.0, None,
                       torch.ones(len(kp), dtype=torch.float64), w, q_ref, 0.0, vel, ori, ow)
        qq = q.clone().requires_grad_()
        cost, D, E, F, g = terms.evaluate(qq)
        (grad,) = torch.autograd.grad(cost.sum(), qq)
        want = cs.pullback(q, grad)
        torch.testing.assert_close(g[..., cols], want[..., cols], atol=1e-8, rtol=1e-8)
        ev = torch.linalg.eigvalsh(D)  # JᵀJ: positive semi-definite
        assert torch.isfinite(D).all() and (ev > -1e-9 * ev.amax(-1, keepdim=True)).all()


def _terms_case(dtype, B=2, T=6):
    """A whole-clip problem on the G1 (random poses near the ground, noisy keypoints, random contacts and
    orientation targets on some frames): its _Terms and q."""
    from diffkin.retarget.whole_clip import COSTS, _Terms, _velocity_limits
    from diffkin.rotations import _skew

    mp = retarget.Mapping.builtin("g1")
    g1 = models.from_urdf(G1_URDF, mp.frames, floating_base=True, dtype=dtype).requires_grad_(False)
    gen = torch.Generator().manual_seed(1)
    q = torch.zeros(B, T, g1.nq, dtype=torch.float64)
    q[..., 2], q[..., 3] = 0.76, 1.0  # some sole points below the ground: penetration rows
    q[..., 7:] = 0.2 * torch.randn(B, T, g1.nq - 7, generator=gen, dtype=torch.float64)
    q[..., 3:7] += 0.05 * torch.randn(B, T, 4, generator=gen, dtype=torch.float64)
    q[..., 3:7] /= q[..., 3:7].norm(dim=-1, keepdim=True)
    kp = mp.keypoint_frames
    with torch.no_grad():
        x = g1.forward_kinematics(q.to(dtype))[..., [g1.end_links.index(f) for f in kp], :3, 3].double()
    x = x + 0.03 * torch.randn(x.shape, generator=gen, dtype=torch.float64)
    contacts = torch.rand(B, T, 2, generator=gen) < 0.7
    rv = 0.5 * torch.randn(B, T, len(kp), 3, generator=gen, dtype=torch.float64)
    R_d = torch.linalg.matrix_exp(_skew(rv))
    ow = torch.rand(len(kp), generator=gen, dtype=torch.float64) * (torch.arange(len(kp)) % 2)  # some 0
    kw = 0.5 + torch.rand(len(kp), generator=gen, dtype=torch.float64)
    q_ref = q.clone()  # the posture rows' reference: near q, not q (rows that are not zero; the base too)
    q_ref[..., :3] += 0.05 * torch.randn(B, T, 3, generator=gen, dtype=torch.float64)
    q_ref[..., 3:7] += 0.1 * torch.randn(B, T, 4, generator=gen, dtype=torch.float64)
    q_ref[..., 3:7] /= q_ref[..., 3:7].norm(dim=-1, keepdim=True)
    q_ref[..., 7:] += 0.05 * torch.randn(B, T, g1.nq - 7, generator=gen, dtype=torch.float64)
    terms = _Terms(g1, x.to(dtype), contacts, list(mp.feet), kp, 30.0, 0.01, None, kw.to(dtype), dict(COSTS),
                   q_ref.to(dtype), 0.0, _velocity_limits(g1, 3.0, q.to(dtype)), R_d.to(dtype), ow.to(dtype))
    return terms, q.to(dtype)


def test_whole_clip_projection_is_the_frame_after_frame_clamp():
    """_Terms.project: the limits, then frame after frame q_t into [q_{t−1} ∓ q̇_max/fps] ∩ [q_min, q_max]
    (a numpy loop over every frame here); a clip within the velocity limits comes back as it is, and one
    whose first step beyond is at frame 3 (in one clip of two) is clamped from there on."""
    terms, q = _terms_case(torch.float64, B=2, T=8)
    sq, vstep = terms.sq.numpy(), terms.vstep.numpy()
    lo, hi = terms.lo_hard.numpy(), terms.hi_hard.numpy()

    def reference(q):
        out = terms.chain.clamp_to_limits(q, check=False).numpy().copy()
        for b in range(out.shape[0]):
            for t in range(1, out.shape[1]):
                prev = out[b, t - 1, sq]
                lo_t, hi_t = np.maximum(prev - vstep, lo), np.minimum(prev + vstep, hi)
                out[b, t, sq] = np.clip(out[b, t, sq], lo_t, hi_t)
        return torch.from_numpy(out)

    slow = q[:, :1].expand(q.shape).clone()  # every frame the first: no step at all
    slow[..., 7:] += 0.05 * torch.linspace(0, 1, q.shape[1], dtype=q.dtype)[:, None]  # 0.007 rad a frame
    slow = terms.chain.clamp_to_limits(slow, check=False)
    assert torch.equal(terms.project(slow), slow)
    jump = slow.clone()
    jump[1, 3:, 7:] += 0.3  # 0.3 rad at frame 3 of clip 1 (the limit: 0.1 rad a frame)
    got = terms.project(jump)
    torch.testing.assert_close(got, reference(jump), rtol=0, atol=1e-15)
    assert torch.equal(got[:, :3], jump[:, :3]) and not torch.equal(got[1, 3:], jump[1, 3:])
    torch.testing.assert_close(terms.project(q), reference(q), rtol=0, atol=1e-15)
    # a run of 20 clamped frames (2 rad at 0.1 rad a frame) and noise clamped at most frames: more than
    # the CPU path's sweeps over all frames at once, the rest frame after frame; the same numbers as the loop
    long_terms, long_q = _terms_case(torch.float64, B=2, T=24)
    far = long_q[:, :1].expand(long_q.shape).clone()
    far[0, 2:, 7:] += 2.0
    noise = torch.randn(24, far.shape[-1] - 7, generator=torch.Generator().manual_seed(0), dtype=far.dtype)
    far[1, :, 7:] += 0.4 * noise  # steps beyond the limit either way at most frames
    far = terms.chain.clamp_to_limits(far, check=False)
    got = long_terms.project(far)
    assert not torch.equal(got[0, 12], far[0, 12])  # still clamped 10 frames after the jump
    torch.testing.assert_close(got, reference(far), rtol=0, atol=0)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_whole_clip_frame_terms_in_c_equal_the_torch_path(dtype):
    """The C frame terms (native.clip_rows: keypoints, orientations, the soles' contact, penetration and
    level rows, skating) and joint terms (native.clip_joint: limits, velocity limits, posture, velocity,
    acceleration) give the torch path's cost, D, E and g: 1e-9 relative in float64; with recycled blocks
    (evaluate(recycle=True), two sets in turn) the same numbers, the third call in the first's."""
    from diffkin.kernels import native

    if not native.available():
        pytest.skip("the native kernel is not built")
    terms, q = _terms_case(dtype)
    assert bool((terms.c[:, 1:] & terms.c[:, :-1]).any())  # skating pairs
    qs = q[..., terms.sq]
    assert bool(((qs > terms.hi) | (qs < terms.lo)).any())  # limit rows active
    assert bool(((qs[:, 1:] - qs[:, :-1]).abs() > terms.vstep).any())  # velocity-limit rows active
    with torch.no_grad():
        Ta, Ja = terms.chain.forward_kinematics_and_jacobian(q.flatten(0, 1))
        h = Ta[:, terms.feet_idx, 2, 3]
    assert bool((h < 0.05).any())  # some frames with soles below the ground
    fast = terms.evaluate(q)
    with native.disabled():
        slow = terms.evaluate(q)
    tol = 1e-9 if dtype == torch.float64 else 1e-4
    for name, a, b in zip(("cost", "D", "E", "F", "g"), fast, slow):
        scale = b.abs().amax().clamp_min(1.0)
        assert (a - b).abs().amax() <= tol * scale, name
    assert fast[2].abs().amax() > 0 and not torch.equal(fast[2], torch.zeros_like(fast[2]))
    # recycled blocks (the LM loop's two sets in turn): the same numbers; the third call writes the first's
    q2 = q + 0.01
    first = terms.evaluate(q, recycle=True)
    second = terms.evaluate(q2, recycle=True)
    for a, b in zip(first, fast):
        assert torch.equal(a, b)
    third = terms.evaluate(q, recycle=True)
    assert third[1].data_ptr() == first[1].data_ptr() and third[1].data_ptr() != second[1].data_ptr()
    for a, b in zip((second, third), (terms.evaluate(q2), fast)):
        for x, y in zip(a, b):
            assert torch.equal(x, y)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_whole_clip_frame_terms_with_the_fk_in_the_same_pass(dtype):
    """evaluate's C path computes the frames' FK inside native.clip_rows, a block of 16 frames at a time
    (no poses nor Jacobians written out): the same floats as clip_rows from the chain's FK outputs, for a
    frame count that leaves a partial block, on one and two threads; a call with rows that need the poses
    (extra_rows) takes the FK outputs."""
    from diffkin.kernels import native

    if not native.available():
        pytest.skip("the native kernel is not built")
    terms, q = _terms_case(dtype, B=3, T=7)  # 21 frames: a block of 16 and one of 5
    B, T, nq = q.shape
    with torch.no_grad():
        Ta, Ja = terms.chain.forward_kinematics_and_jacobian(q.reshape(B * T, nq), check=False)
        from_fk = terms._joint_terms(q, *terms.frame_terms(Ta, Ja, B, T))
        calls = []
        clip_rows = native.clip_rows

        def spy(Tf, J, **kw):
            calls.append(Tf is None and kw.get("fk") is not None)
            return clip_rows(Tf, J, **kw)

        native.clip_rows = spy
        try:
            for threads in (1, 2):
                with native.threads(threads):
                    fused = terms.evaluate(q)
                for name, a, b in zip(("cost", "D", "E", "F", "g"), fused, from_fk):
                    assert torch.equal(a, b), (name, threads)
            assert calls == [True, True]
            terms.extra_rows = [lambda q_, Ta_, Ja_: (Ta_.new_zeros(B, T, 1),
                                                      Ja_.new_zeros(B, T, 1, Ja_.shape[-1]))]
            with_rows = terms.evaluate(q)
            assert calls[-1] is False
        finally:
            native.clip_rows = clip_rows
    for a, b in zip(with_rows, from_fk):
        assert torch.equal(a, b)


@pytest.mark.parametrize("source", ["urdf", "mjcf"])
def test_jacobian_support_holds_every_non_zero_column(source):
    """native.jacobian_support (the columns of each end link's ancestors) covers every non-zero Jacobian
    column at random poses, and each of its columns is non-zero at some pose (it is the support, not a
    superset), for the URDF and MJCF G1 with the retargeting frames; and the C frame terms give the same
    numbers with it as with each frame's support found from its Jacobian (the same floats)."""
    from diffkin.kernels import native

    mp = retarget.Mapping.builtin("g1")
    if source == "urdf":
        g1 = models.from_urdf(G1_URDF, mp.frames, floating_base=True, dtype=torch.float64)
    else:
        g1 = models.from_mjcf(models.model_path("g1"), mp.frames, dtype=torch.float64)
    g1 = g1.requires_grad_(False)
    q = g1.random_configuration(64, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        _, J = g1.forward_kinematics_and_jacobian(q)
    nonzero = (J != 0).any(-2).any(0)  # (E, nv)
    sup = native.jacobian_support(g1.topology, g1.nv)
    assert torch.equal(sup, nonzero)
    assert not bool(sup.all())  # a tree: every end link misses some columns
    if source == "urdf" and native.available():
        terms, qc = _terms_case(torch.float64)
        given = terms.evaluate(qc)
        terms.support = None
        terms._clip_args.clear()  # the C call's converted constants, support among them
        found = terms.evaluate(qc)
        for a, b in zip(given, found):
            assert torch.equal(a, b)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_whole_clip_step_in_c_equals_the_torch_path(dtype):
    """The LM trial in C (native.clip_step: q ⊕ step with the base quaternion turned, the limits, then the
    velocity limits frame after frame) equals project(integrate(q, step)) in torch: 1e-12 in float64; steps
    large enough that both clamps act, turns of the base of 0 and near 0 (sinc's Taylor branch) and larger
    ones."""
    from diffkin.kernels import native

    if not native.available():
        pytest.skip("the native kernel is not built")
    terms, q = _terms_case(dtype, B=2, T=9)
    gen = torch.Generator().manual_seed(3)
    step = 0.3 * torch.randn(*q.shape[:2], terms.chain.nv, generator=gen, dtype=torch.float64).to(dtype)
    step[0, :, 3:6] *= 1e-6  # a tiny turn of the base in clip 0, none at all in its first frames
    step[0, :2, 3:6] = 0.0
    fast = terms.step(q, step)
    with native.disabled():
        slow = terms.step(q, step)
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    torch.testing.assert_close(fast, slow, rtol=0, atol=tol)
    moved = terms.chain.configuration_space.integrate(q, step)
    qs, ms = fast[..., terms.sq], moved[..., terms.sq]
    assert bool((qs != ms).any())  # some coordinate clamped
    assert bool(((qs[:, 1:] - qs[:, :-1]).abs() >= terms.vstep * (1 - 1e-6)).any())  # at its velocity limit
    assert not torch.equal(fast[..., 3:7], q[..., 3:7])  # the base turned


def test_whole_clip_optimisation_in_c_equals_the_torch_path(monkeypatch):
    """optimize_clip from one warm start (12 frames of the shipped hop, velocity limits, 3 iterations) gives
    the same clip with the C kernels (frame terms, banded solve, FK) as with the torch path: 1e-9; and the
    same on two C threads (``threads=2``) as on one."""
    from diffkin.kernels import native

    if not native.available():
        pytest.skip("the native kernel is not built")
    mp = retarget.Mapping.builtin("g1")
    g1 = models.from_urdf(G1_URDF, mp.frames, floating_base=True, dtype=torch.float64)
    hop = retarget.load_bvh(retarget.example_clips()["hop"]).frames_slice(0, 12)
    r = retarget.clip(g1, hop, mp, whole_clip=False)

    def run(**kw):
        return retarget.optimize_clip(g1, r.q, r.keypoints, r.contacts, feet=mp.feet,
                                      keypoint_frames=r.keypoint_frames, fps=hop.fps, iterations=3,
                                      velocity_limit=20.0, **kw)

    fast = run()
    with native.disabled():
        slow = run()
    assert bool((fast.cost[-1] < fast.cost[0] / 2).all())
    torch.testing.assert_close(fast.cost, slow.cost, rtol=1e-9, atol=0)
    torch.testing.assert_close(fast.q, slow.q, rtol=0, atol=1e-9)
    # threads=2: the kernels share the frames out over two threads (two cores free, as the policy sees it)
    # whatever torch's count; the same clip
    counts = []
    count = native.thread_count
    monkeypatch.setattr(native, "thread_count", lambda *a, **k: counts.append(count(*a, **k)) or counts[-1])
    monkeypatch.setattr(native, "free_cores", lambda: 2)
    two = run(threads=2)
    assert max(counts) == 2
    torch.testing.assert_close(two.cost, fast.cost, rtol=1e-12, atol=0)
    torch.testing.assert_close(two.q, fast.q, rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="threads"):
        run(threads=0)


def test_whole_clip_extra_rows_plug_in():
    """The residual-row interface: per-frame rows given through ``extra_rows`` add ½‖r‖² to the cost, JᵀJ
    to D and Jᵀr to g (a row that repeats the pelvis keypoint's rows doubles their share)."""
    terms, q = _terms_case(torch.float64, B=1, T=4)
    base = terms.evaluate(q)
    k = terms.kp_idx[0]
    sw = terms.w["keypoint"] * terms.kp_w[0]

    def pelvis(q_, Ta, Ja):
        return sw * (Ta[..., k, :3, 3] - terms.x[:, :, 0]), sw * Ja[..., k, :3, :]

    terms.extra_rows.append(pelvis)
    more = terms.evaluate(q)
    Ta, Ja = terms.chain.forward_kinematics_and_jacobian(q.flatten(0, 1))
    r, J = pelvis(q, Ta.reshape(1, 4, *Ta.shape[1:]), Ja.reshape(1, 4, *Ja.shape[1:]))
    torch.testing.assert_close(more[0] - base[0], 0.5 * r.square().sum((-1, -2)))
    torch.testing.assert_close(more[1] - base[1], J.mT @ J)
    torch.testing.assert_close(more[4] - base[4], (J.mT @ r.unsqueeze(-1)).squeeze(-1))
    torch.testing.assert_close(more[2], base[2])


def test_whole_clip_orientation_targets_recover_the_wrists():
    """Orientation targets (the robot's own link frames by diffkin FK): the wrist joints, which positions of
    the wrist_yaw_link origin leave nearly unobservable, are recovered with the orientation term and not
    without it; the term's frames are exactly where MuJoCo-free FK puts them (rotation angle < 1°)."""
    from diffkin.kernels.pose_error import rotation_angle

    mp = retarget.Mapping.builtin("g1")
    g1 = models.from_urdf(G1_URDF, mp.frames, floating_base=True, dtype=torch.float64)
    T = 8
    q = torch.zeros(1, T, g1.nq, dtype=torch.float64)
    q[..., 2], q[..., 3] = 0.793, 1.0
    col = {n: 7 + i for i, n in enumerate(g1.joint_names[1:])}
    s = torch.linspace(0, 1, T, dtype=torch.float64)
    wrists = ("left_wrist_roll_joint", "right_wrist_pitch_joint", "left_elbow_joint")
    for j, amp in zip(wrists, (0.8, -0.6, 0.5)):
        q[0, :, col[j]] = amp * s
    kp = mp.keypoint_frames
    idx = [g1.end_links.index(f) for f in kp]
    with torch.no_grad():
        Tk = g1.forward_kinematics(q)[..., idx, :, :]
    start = q.clone()
    start[..., 7:] = 0.0  # the standing posture: the arm motion is to be found
    c = torch.ones(1, T, 2, dtype=torch.bool)
    kw = dict(feet=mp.feet, keypoint_frames=kp, fps=30.0, iterations=8)
    with_o = retarget.optimize_clip(g1, start, Tk[..., :3, 3], c, orientations=Tk[..., :3, :3],
                                    orientation_weights=[1.0] * len(kp), costs={"orientation": 1.0}, **kw)
    without = retarget.optimize_clip(g1, start, Tk[..., :3, 3], c, **kw)
    for j in wrists:
        torch.testing.assert_close(with_o.q[0, :, col[j]], q[0, :, col[j]], atol=2e-2, rtol=0)
    assert (without.q[0, -1, col["left_wrist_roll_joint"]] - 0.8).abs() > 0.2
    with torch.no_grad():
        got = g1.forward_kinematics(with_o.q)[..., idx, :3, :3]
    assert rotation_angle(Tk[..., :3, :3], got).max() < math.radians(1.0)
    with pytest.raises(ShapeError, match="orientations"):
        retarget.optimize_clip(g1, start, Tk[..., :3, 3], c, orientations=Tk[:, :2, :, :3, :3], **kw)
    with pytest.raises(OptionError, match="orientation weights"):
        retarget.optimize_clip(g1, start, Tk[..., :3, 3], c, orientations=Tk[..., :3, :3],
                               orientation_weights=[-1.0] * len(kp), **kw)


def test_clip_follows_human_orientations_with_orientation_weights():
    """Mapping weights (w_pos, w_ori) > 0 on the wrists: clip follows the human wrists' frames (the BVH's
    orientations) up to their fitted constant offsets more closely than with w_ori = 0."""
    from diffkin.kernels.pose_error import rotation_angle
    from diffkin.retarget.clip import _orientation_targets

    mp0 = retarget.Mapping.builtin("g1")
    g1 = models.from_urdf(G1_URDF, mp0.frames, floating_base=True, dtype=torch.float64)
    hop = retarget.load_bvh(retarget.example_clips()["hop"]).frames_slice(0, 12)
    mp = retarget.Mapping(mp0.pairs, feet=mp0.feet, contact_joints=mp0.contact_joints,
                          weights={f"{s}_wrist_yaw_link": (1.0, 3.0) for s in ("left", "right")})
    plain = retarget.clip(g1, hop, mp0, warm_start="batched", max_iterations=8, iterations=4)
    ori = retarget.clip(g1, hop, mp, warm_start="batched", max_iterations=8, iterations=4)
    frames = ["left_wrist_yaw_link", "right_wrist_yaw_link"]
    k = [mp.keypoint_frames.index(f) for f in frames]

    def spread(r):  # the wrists' deviation from the human's frames times the constant offsets fitted on r.q
        target = _orientation_targets(g1, hop, mp, r.q)[:, :, k]
        with torch.no_grad():
            R = g1.forward_kinematics(r.q)[..., [g1.end_links.index(f) for f in frames], :3, :3]
        return rotation_angle(target, R).mean()

    assert spread(ori) < 0.3 * spread(plain)  # 0.7° against 5.4° when written
    assert int(ori.metrics.joint_limit_violations) == 0 and ori.metrics.keypoint_error.item() < 80.0


def test_optimize_clip_errors():
    mp = retarget.Mapping.builtin("g1")
    g1 = models.from_urdf(G1_URDF, mp.frames, floating_base=True, dtype=torch.float64)
    q = torch.zeros(1, 3, g1.nq, dtype=torch.float64)
    q[..., 3] = 1.0
    kp = mp.keypoint_frames
    x = torch.zeros(1, 3, len(kp), 3, dtype=torch.float64)
    c = torch.ones(1, 3, 2, dtype=torch.bool)
    kw = dict(feet=mp.feet, keypoint_frames=kp, fps=30.0)
    with pytest.raises(ShapeError, match="keypoints"):
        retarget.optimize_clip(g1, q, x[:, :2], c, **kw)
    with pytest.raises(ShapeError, match="contacts"):
        retarget.optimize_clip(g1, q, x, c[..., :1], **kw)
    with pytest.raises(ModelError, match="skate"):
        retarget.optimize_clip(g1, q, x, c, costs={"skate": 1.0}, **kw)
    with pytest.raises(OptionError, match="solver"):
        retarget.optimize_clip(g1, q, x, c, solver="qr", **kw)
    with pytest.raises(ModelError, match="nofoot"):
        retarget.optimize_clip(g1, q, x, c, feet=("nofoot", mp.feet[1]), keypoint_frames=kp, fps=30.0)
    with pytest.raises(OptionError, match="fps"):
        retarget.optimize_clip(g1, q, x, c, feet=mp.feet, keypoint_frames=kp, fps=0)
    with pytest.raises(NonFiniteError, match="contacts"):
        retarget.optimize_clip(g1, q, x, torch.full((1, 3, 2), math.nan, dtype=torch.float64), **kw)
    with pytest.raises(NonFiniteError, match="keypoint_weights"):
        retarget.optimize_clip(g1, q, x, c, keypoint_weights=[math.nan] * len(kp), **kw)
    with pytest.raises(OptionError, match="keypoint_weights"):
        retarget.optimize_clip(g1, q, x, c, keypoint_weights=[-1.0] * len(kp), **kw)
    with pytest.raises(OptionError, match="costs"):
        retarget.optimize_clip(g1, q, x, c, costs={next(iter(retarget.COSTS)): -1.0}, **kw)
    # float32 keypoints with a float64 chain: taken in the chain's dtype
    f32 = retarget.optimize_clip(g1, q, x.float(), c, iterations=1, **kw)
    assert f32.q.dtype == torch.float64
    out = retarget.optimize_clip(g1, q, x, c, iterations=0, **kw)
    torch.testing.assert_close(out.q[..., 3:], q[..., 3:])  # iterations=0: the warm start, lifted ...
    T_out = g1.forward_kinematics(out.q)
    lowest = min(retarget.sole_of(g1, f).lowest(T_out[..., g1.end_links.index(f), :, :])[0].min()
                 for f in mp.feet)
    assert abs(lowest.item()) <= 1e-12 and bool((out.q[..., 2] > q[..., 2]).all())  # ... onto the ground
    assert out.cost.shape == (1, 1)
    with pytest.raises(ModelError, match="nojoint"):
        retarget.optimize_clip(g1, q, x, c, velocity_limit={"nojoint": 1.0}, **kw)
    with pytest.raises(OptionError, match="collision_margin"):
        retarget.optimize_clip(g1, q, x, c, collision_margin=-0.01, **kw)
    with pytest.raises(ModelError, match="RobotCollision"):
        retarget.optimize_clip(g1, q, x, c, collision=object(), **kw)
    with pytest.raises(OptionError, match="velocity_limit"):
        retarget.optimize_clip(g1, q, x, c, velocity_limit=0.0, **kw)
    with pytest.raises(ShapeError, match="velocity_limit"):
        retarget.optimize_clip(g1, q, x, c, velocity_limit=[1.0, 2.0], **kw)
    cg = retarget.optimize_clip(g1, q, x, c, iterations=2, solver="cg", **kw)
    assert cg.cost[-1].item() < cg.cost[0].item()


def test_whole_clip_difference_terms_hessian_by_differences():
    """The banded normal matrix (D, E, F) of the terms that couple frames (velocity limits, velocity,
    acceleration; every other weight 0) is their cost's Hessian in the hinge columns (central differences
    of the gradient): the residuals are (piecewise) linear there, so Gauss–Newton's JᵀJ is exact."""
    from diffkin.retarget.whole_clip import COSTS, _Terms, _velocity_limits

    mp = retarget.Mapping.builtin("g1")
    g1 = models.from_urdf(G1_URDF, mp.frames, floating_base=True, dtype=torch.float64)
    B, T = 1, 3  # T = 3: the F band (t, t − 2) is in
    gen = torch.Generator().manual_seed(1)
    q = torch.zeros(B, T, g1.nq, dtype=torch.float64)
    q[..., 2], q[..., 3] = 0.78, 1.0
    q[..., 7:] = 0.2 * torch.randn(B, T, g1.nq - 7, generator=gen, dtype=torch.float64)
    kp = mp.keypoint_frames
    x = torch.zeros(B, T, len(kp), 3, dtype=torch.float64)
    c = torch.zeros(B, T, 2, dtype=torch.bool)
    w = {k: 0.0 for k in COSTS} | {"velocity_limit": 10.0, "velocity": 0.3, "acceleration": 0.5}
    terms = _Terms(g1, x, c, list(mp.feet), kp, 30.0, 0.0, None, torch.ones(len(kp), dtype=torch.float64), w,
                   q.clone(), 0.0, _velocity_limits(g1, 3.0, q))
    _, D, E, F, _ = terms.evaluate(q)
    n = g1.nv
    H = torch.zeros(T * n, T * n, dtype=torch.float64)
    for t in range(T):  # the dense matrix of the lower blocks (a loop over the 3 frames of a test)
        H[t * n:(t + 1) * n, t * n:(t + 1) * n] = D[0, t]
        for k, M in ((1, E[0]), (2, F)):  # F: one band for every clip
            if t >= k:
                H[t * n:(t + 1) * n, (t - k) * n:(t - k + 1) * n] = M[t]
                H[(t - k) * n:(t - k + 1) * n, t * n:(t + 1) * n] = M[t].T

    # central differences of the gradient g (checked against autograd in the test above) in the hinges of
    # all three frames, where the terms are linear pieces: exact to rounding. The limit term acts on the
    # hinges whose steps exceed 0.1 rad; four of them (and one below it) in every frame:
    step = q[0, :, 7:].diff(dim=0).abs().amax(0)  # (29,): the largest step of each hinge
    hinges = [int(i) for i in step.argsort(descending=True)[:4]] + [int(step.argmin())]
    eps = 1e-6
    cols = [t * n + 6 + j for t in range(T) for j in hinges]
    want = torch.zeros(T * n, len(cols), dtype=torch.float64)
    for i, col in enumerate(cols):
        t, j = divmod(col, n)
        dq = torch.zeros_like(q)
        dq[0, t, 7 + j - 6] = eps
        want[:, i] = (terms.evaluate(q + dq)[4] - terms.evaluate(q - dq)[4]).reshape(-1) / (2 * eps)
    torch.testing.assert_close(H[:, cols], want, atol=1e-6, rtol=1e-6)  # whole columns: D, E and F blocks
    assert bool((step[hinges[:4]] > 0.1).all())  # 3 rad/s at 30 fps: the limit term is active on them


def test_whole_clip_velocity_limits_are_hard():
    """velocity_limit: unconstrained, the first 16 frames of the shipped walk reach 12 rad/s; with a limit for
    every hinge and a tighter one for the knees the output's finite differences (numpy) stay within them,
    the joint limits hold and the contacts are kept."""
    mp = retarget.Mapping.builtin("g1")
    g1 = models.from_urdf(G1_URDF, mp.frames, floating_base=True, dtype=torch.float64)
    walk = retarget.load_bvh(retarget.example_clips()["walk"]).frames_slice(0, 16)
    free = retarget.clip(g1, walk, mp, warm_start="batched", max_iterations=8, iterations=3)
    assert free.metrics.max_joint_velocity.item() > 10.0
    names = list(g1.joint_names[1:])
    limit = {n: 8.0 for n in names} | {"left_knee_joint": 4.0, "right_knee_joint": 4.0}
    r = retarget.clip(g1, walk, mp, warm_start="batched", max_iterations=8, iterations=3,
                      velocity_limit=limit)
    qd = np.abs(np.diff(r.q[0, :, 7:].numpy(), axis=0)) * walk.fps  # the hinges (free joint first)
    bound = np.array([limit[n] for n in names])
    assert (qd <= bound * (1 + 1e-9)).all() and (qd >= bound * (1 - 1e-6)).any()  # reached: it binds
    assert int(r.metrics.joint_limit_violations) == 0
    assert r.metrics.foot_skating.item() <= 10.0 and r.metrics.ground_penetration.item() <= 1.0
    assert r.metrics.keypoint_error.item() < 80.0


def test_clip_batched_warm_start():
    """warm_start="batched": every frame in one ik.solve call, each from the standing posture at its own
    root and heading: the keypoints are reached as closely as frame by frame (47 mm on the whole walk)."""
    mp = retarget.Mapping.builtin("g1")
    g1 = models.from_urdf(G1_URDF, mp.frames, floating_base=True, dtype=torch.float64)
    walk = retarget.load_bvh(retarget.example_clips()["walk"]).frames_slice(0, 12)
    r = retarget.clip(g1, walk, mp, warm_start="batched", whole_clip=False)
    assert r.warm_start is None and r.cost is None and torch.isfinite(r.q).all()
    assert int(r.metrics.joint_limit_violations) == 0
    assert r.metrics.keypoint_error.item() < 50.0  # mm
    with pytest.raises(OptionError, match="warm_start"):
        retarget.clip(g1, walk, mp, warm_start="parallel")


def test_the_builtin_g1_mapping_on_menageries_current_g1():
    """The issue's robot: ``models.load("g1")`` is MuJoCo Menagerie's current 29-DoF unitree_g1 (shipped); the
    built-in mapping's frames are its bodies, its foot spheres give the sole (3 cm below the ankle-roll
    origin, 5 mm spheres: 3.5 cm), and a short clip retargets onto it with its limits and contacts kept."""
    mp = retarget.Mapping.builtin("g1")
    g1 = models.from_mjcf(models.model_path("g1"), mp.frames, dtype=torch.float64)
    assert g1.nq == 36 and "waist_pitch_joint" in g1.joint_names and "torso_joint" not in g1.joint_names
    for foot in mp.feet:
        sole = retarget.sole_of(g1, foot)
        lowest = (sole.points[:, 2] - sole.radii).min().item()
        assert lowest == pytest.approx(-0.035, abs=1e-12)
    hop = retarget.load_bvh(retarget.example_clips()["hop"]).frames_slice(0, 12)
    r = retarget.clip(g1, hop, mp, max_iterations=8, iterations=4)
    m = r.metrics
    assert int(m.joint_limit_violations) == 0 and m.ground_penetration.item() <= 1.0
    assert m.foot_skating.item() <= 5.0 and m.floating.item() <= 5.0 and m.keypoint_error.item() < 80.0


# ------------------------------------------------------------------------------------------ picture
def test_plot_frame_draws_the_robot_at_its_fk_and_the_human_beside_it(tmp_path):
    """retarget.plot_frame: the robot's lines are its FK segments (the free joint's slides left out, so no
    line leaves the world origin) and pass through every mapped frame; the human's lines are the clip's
    bones at their lengths, moved ``gap`` sideways from the robot's keypoints; a PNG is written."""
    pytest.importorskip("matplotlib")
    from diffkin.viz import segment_points

    mp = retarget.Mapping.builtin("g1")
    g1 = models.load_chain("g1", end_link=mp.frames, dtype=torch.float64).requires_grad_(False)
    walk = retarget.load_bvh(retarget.example_clips()["walk"]).frames_slice(20, 23)
    r = retarget.clip(g1, walk, mp, whole_clip=False)
    fig = retarget.plot_frame(g1, r, walk, 1, gap=0.7, path=tmp_path / "f.png")
    assert (tmp_path / "f.png").stat().st_size > 10_000
    ax = fig.axes[0]
    robot = [np.stack(h.get_data_3d(), -1) for h in ax.lines if h.get_color() == "tab:orange" and
             len(h.get_xdata())]
    human = [np.stack(h.get_data_3d(), -1) for h in ax.lines if h.get_color() == "tab:blue" and
             len(h.get_xdata())]
    F = g1.forward_kinematics(r.q[0, 1], all_frames=True).numpy()
    E = g1.forward_kinematics(r.q[0, 1]).numpy()
    want = segment_points(g1, F, E, floating=False)
    assert len(robot) == len(want) == len(segment_points(g1, F, E)) - 4  # x, y, z slides and the ball
    np.testing.assert_allclose(np.stack(robot), want, atol=1e-12)
    assert np.linalg.norm(np.stack(robot).reshape(-1, 3), axis=-1).min() > 0.1  # nothing at the origin
    ends = np.stack(robot).reshape(-1, 3)
    for k, f in enumerate(g1.end_links):
        assert np.linalg.norm(ends - E[k, :3, 3], axis=-1).min() < 1e-12, f
    p = walk.positions[0, 1].numpy()
    bones = [j for j, parent in enumerate(walk.parents) if parent >= 0]
    assert len(human) == len(bones)
    np.testing.assert_allclose([np.linalg.norm(h[1] - h[0]) for h in human],
                               [np.linalg.norm(p[j] - p[walk.parents[j]]) for j in bones], atol=1e-12)
    shift = np.stack([h[1] - p[j] for h, j in zip(human, bones)])  # one horizontal translation
    np.testing.assert_allclose(shift, np.broadcast_to(shift[0], shift.shape), atol=1e-12)
    assert abs(shift[0, 2]) < 1e-12
    kp = r.keypoints[0, 1].numpy()
    assert np.linalg.norm((p + shift[0]).mean(0)[:2] - kp.mean(0)[:2]) == pytest.approx(0.7, abs=1e-9)
    with pytest.raises(ShapeError, match="frame 3"):
        retarget.plot_frame(g1, r, walk, 3)


@pytest.mark.parametrize("tilted", [False, True])
def test_lift_above_ground_along_the_worlds_z(tilted):
    """The ground lift raises the floating base along the world's z, also when the chain's base frame is
    rotated (q's base position is in that frame): afterwards the lowest sole point is on the ground to
    rounding where it was below, and untouched where it was above (it used to add to q's own z: 6 cm off
    with a tilted base)."""
    from diffkin.retarget.ground import lift_above_ground, soles_of
    from diffkin.rotations import rot_x

    chain = models.from_mjcf(FEET_XML, ["lfoot", "rfoot", "arm"], dtype=torch.float64)
    if tilted:
        base = torch.eye(4, dtype=torch.float64)
        base[:3, :3] = rot_x(torch.tensor(0.7, dtype=torch.float64))
        base[:3, 3] = torch.tensor([0.1, -0.2, 0.05])
        chain.base = base
    q = torch.zeros(4, 15, dtype=torch.float64)
    q[:, 3] = q[:, 10] = 1.0
    q[:, 2] = torch.tensor([-0.3, -0.02, 0.0, 0.4])  # some soles below the ground, one well above
    q[:, 9] = 1.0
    soles = soles_of(chain, ["lfoot"])

    def lowest(q):
        T = chain.forward_kinematics(q)[..., 0, :, :]
        return soles[0].lowest(T, 0.0)[0]

    before, after = lowest(q), lowest(lift_above_ground(chain, q, ["lfoot"], soles, 0.0))
    below = before < 0
    assert bool(below.any()) and bool((~below).any())
    torch.testing.assert_close(after[below], torch.zeros_like(after[below]), rtol=0, atol=1e-12)
    assert torch.equal(after[~below], before[~below])

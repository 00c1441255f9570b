"""Which robot frame follows which human joint: :class:`Mapping`, and the built-in mappings."""

from __future__ import annotations

from collections.abc import Mapping as _MappingABC
from collections.abc import Sequence

import torch
from torch import Tensor

from ..errors import ConventionError, ModelError, ShapeError
from ..validation import as_tensor
from .contacts import detect_contacts
from .motion import Motion
from .sole import Sole

__all__ = ["BUILTIN", "Mapping", "SKELETONS", "skeleton_of"]

_SIDES = ("left", "right")


def _g1(human: dict[str, str]) -> dict[str, str]:
    """The 29-DoF G1's bodies (MuJoCo Menagerie's current ``unitree_g1``, Unitree's g1_29dof URDF)."""
    pairs = {"pelvis": human["pelvis"], "torso_link": human["chest"]}
    for s in _SIDES:
        pairs |= {f"{s}_hip_roll_link": human[f"{s}_hip"], f"{s}_knee_link": human[f"{s}_knee"],
                  f"{s}_ankle_roll_link": human[f"{s}_ankle"],
                  f"{s}_shoulder_roll_link": human[f"{s}_shoulder"], f"{s}_elbow_link": human[f"{s}_elbow"],
                  f"{s}_wrist_yaw_link": human[f"{s}_wrist"]}
    return pairs


def _h1(human: dict[str, str]) -> dict[str, str]:
    """Unitree H1 (MuJoCo Menagerie's ``unitree_h1``: no wrists, feet ``*_ankle_link``)."""
    pairs = {"pelvis": human["pelvis"], "torso_link": human["chest"]}
    for s in _SIDES:
        pairs |= {f"{s}_hip_roll_link": human[f"{s}_hip"], f"{s}_knee_link": human[f"{s}_knee"],
                  f"{s}_ankle_link": human[f"{s}_ankle"],
                  f"{s}_shoulder_roll_link": human[f"{s}_shoulder"], f"{s}_elbow_link": human[f"{s}_elbow"]}
    return pairs


#: human skeletons: role -> joint name. ``"cmu"``: the shipped clips of subject 131 (CMU database,
#: 3dsMax-friendly BVH names); ``"cmu_mb"``: the shipped walk-and-turn and pick-up clips (the same CMU
#: skeleton in the MotionBuilder-friendly conversion's names: ``LeftUpLeg`` for ``LeftHip``, ``Spine`` for
#: ``Chest``, ``LeftArm`` for ``LeftShoulder``...); ``"smpl"``: SMPL / SMPL-H / SMPL-X joints
#: (:data:`~diffkin.retarget.smpl.SMPLX_JOINT_NAMES`). :func:`skeleton_of` tells them apart.
SKELETONS = {
    "cmu": {"pelvis": "Hips", "chest": "Chest", "left_hip": "LeftHip", "left_knee": "LeftKnee",
            "left_ankle": "LeftAnkle", "left_toe": "LeftToe", "left_shoulder": "LeftShoulder",
            "left_elbow": "LeftElbow", "left_wrist": "LeftWrist", "right_hip": "RightHip",
            "right_knee": "RightKnee", "right_ankle": "RightAnkle", "right_toe": "RightToe",
            "right_shoulder": "RightShoulder", "right_elbow": "RightElbow", "right_wrist": "RightWrist"},
    "cmu_mb": {"pelvis": "Hips", "chest": "Spine", **{
        f"{s}_{r}": f"{s.title()}{j}" for s in _SIDES for r, j in (
            ("hip", "UpLeg"), ("knee", "Leg"), ("ankle", "Foot"), ("toe", "ToeBase"), ("shoulder", "Arm"),
            ("elbow", "ForeArm"), ("wrist", "Hand"))}},
    "smpl": {"pelvis": "pelvis", "chest": "spine3", **{f"{s}_{r}": f"{s}_{r}" for s in _SIDES for r in (
        "hip", "knee", "ankle", "shoulder", "elbow", "wrist")}, "left_toe": "left_foot",
             "right_toe": "right_foot"},
}
#: robot name -> (pairs builder, (left foot, right foot))
BUILTIN = {"g1": (_g1, ("left_ankle_roll_link", "right_ankle_roll_link")),
           "h1": (_h1, ("left_ankle_link", "right_ankle_link"))}


class Mapping:
    """Robot frames paired with human joints.

    Args:
        pairs: ``{robot frame: human joint name}``; a robot frame is any body or site of the model.
        feet: ``(left, right)`` robot foot frames (in ``pairs`` or not).
        weights: optional ``{robot frame: w}`` (a position weight) or ``{robot frame: (w_pos, w_ori)}``;
            unnamed frames weigh ``(1, 0)``.
        offsets: optional ``{robot frame: (dx, dy, dz)}``, metres added to the human joint's position in
            the world frame (z up); unnamed frames 0.
        contact_joints: ``(left, right)`` human joints whose height and speed decide each foot's contact
            (each a name or a list of names); default the human joints paired with the feet.
        sole: optional ``{foot: Sole}`` replacing the soles read from the model.

    ``frames`` lists the robot frames, feet first, so ``models.from_mjcf(path, mapping.frames)`` is the
    chain retargeting takes; ``weights (K, 2)`` and ``offsets (K, 3)`` follow that order.
    """

    def __init__(self, pairs: dict, *, feet: Sequence[str], weights: dict | None = None,
                 offsets: dict | None = None, contact_joints: Sequence | None = None,
                 sole: dict | None = None):
        if not isinstance(pairs, _MappingABC) or not pairs:
            raise ModelError(f"pairs must be a non-empty dict {{robot frame: human joint}}, got {pairs!r}")
        for k, v in pairs.items():
            if not isinstance(k, str) or not isinstance(v, str):
                raise ModelError(f"pairs must map robot frame names to human joint names (str), got "
                                 f"{k!r}: {v!r}")
        feet = list(feet) if not isinstance(feet, str) else [feet]
        if len(feet) != 2 or not all(isinstance(f, str) for f in feet) or feet[0] == feet[1]:
            raise ModelError(f"feet must be two different robot frames (left, right), got {feet}")
        self.pairs = dict(pairs)
        self.feet = tuple(feet)
        self.frames = [*feet, *(f for f in pairs if f not in feet)]
        for name, table in (("weights", weights), ("offsets", offsets), ("sole", sole)):
            unknown = sorted(set(table or {}) - set(self.frames))
            if unknown:
                raise ModelError(f"{name} names frames {unknown} that are not in the mapping {self.frames}")
        w = []
        for f in self.frames:
            v = (weights or {}).get(f, (1.0, 0.0))
            v = (float(v), 0.0) if isinstance(v, int | float) else tuple(float(x) for x in v)
            if len(v) != 2 or min(v) < 0:
                raise ShapeError(f"weights[{f!r}] must be w >= 0 or (w_pos, w_ori) >= 0, got {v}")
            w.append(v)
        self.weights = torch.tensor(w, dtype=torch.float64)
        self.offsets = torch.zeros(len(self.frames), 3, dtype=torch.float64)
        for f, o in (offsets or {}).items():
            o = as_tensor(o, f"offsets[{f!r}]", dtype=torch.float64).reshape(-1)
            if o.shape != (3,):
                raise ShapeError(f"offsets[{f!r}] must be (dx, dy, dz), got {tuple(o.shape)} values")
            self.offsets[self.frames.index(f)] = o
        if contact_joints is None:
            missing = [f for f in feet if f not in pairs]
            if missing:
                raise ModelError(f"feet {missing} have no human joint in pairs: give "
                                 "contact_joints=(left, right)")
            contact_joints = (pairs[feet[0]], pairs[feet[1]])
        self.contact_joints = tuple(contact_joints)
        if len(self.contact_joints) != 2:
            raise ModelError(f"contact_joints must be (left, right), got {self.contact_joints}")
        for f, s in (sole or {}).items():
            if not isinstance(s, Sole):
                raise ModelError(f"sole[{f!r}] must be a Sole(points, radii), got {type(s).__name__}")
        self.sole = dict(sole or {})

    def __repr__(self) -> str:
        return f"Mapping({len(self.frames)} frames, feet={self.feet})"

    @property
    def keypoint_frames(self) -> list[str]:
        """The frames paired with a human joint, in ``frames`` order."""
        return [f for f in self.frames if f in self.pairs]

    @property
    def human_joints(self) -> list[str]:
        """The human joints of :attr:`keypoint_frames`, in that order."""
        return [self.pairs[f] for f in self.keypoint_frames]

    def check(self, motion: Motion) -> None:
        """Raise :class:`~diffkin.errors.ModelError` naming the mapping's human joints the clip lacks."""
        needed = [*self.human_joints]
        for c in self.contact_joints:
            needed += [c] if isinstance(c, str) else list(c)
        unknown = sorted({n for n in needed if n not in motion.names})
        if unknown:
            raise ModelError(f"the mapping names human joints {unknown} that the clip does not have; its "
                             f"joints are {motion.names}")

    def targets(self, motion: Motion, scale=1.0) -> Tensor:
        """Keypoint targets ``(B, T, K, 3)`` for :attr:`keypoint_frames`: the human joints' positions
        times ``scale`` (a number or ``(B,)``) plus the frames' offsets."""
        self.check(motion)
        p = motion.positions[:, :, motion.index(self.human_joints)]
        s = as_tensor(scale, "scale", dtype=p.dtype, device=p.device).reshape(-1, 1, 1, 1)
        idx = [self.frames.index(f) for f in self.keypoint_frames]
        return p * s + self.offsets[idx].to(p)

    def contacts(self, motion: Motion, **thresholds) -> Tensor:
        """Foot contacts ``(B, T, 2)`` of the human clip (:func:`~diffkin.retarget.detect_contacts` with
        :attr:`contact_joints`; ``height=``, ``speed=``, ``ground=`` override its thresholds)."""
        self.check(motion)
        return detect_contacts(motion, self.contact_joints, **thresholds)

    @classmethod
    def builtin(cls, name: str, skeleton: str = "cmu") -> Mapping:
        """The mapping of robot ``name`` (``"g1"``: the 29-DoF G1; ``"h1"``) for a human ``skeleton``
        (:data:`SKELETONS`: ``"cmu"``, ``"cmu_mb"``, ``"smpl"``; :func:`skeleton_of` finds a clip's). Feet
        contact on the ankle and toe joints."""
        if name not in BUILTIN:
            raise ConventionError(f"no built-in mapping {name!r}; known: {sorted(BUILTIN)}")
        if skeleton not in SKELETONS:
            raise ConventionError(f"unknown skeleton {skeleton!r}; known: {sorted(SKELETONS)}")
        build, feet = BUILTIN[name]
        human = SKELETONS[skeleton]
        contact = ([human["left_ankle"], human["left_toe"]], [human["right_ankle"], human["right_toe"]])
        return cls(build(human), feet=feet, contact_joints=contact)


def skeleton_of(names) -> str:
    """The key of :data:`SKELETONS` whose joints are all among ``names`` (a clip's joint names, e.g.
    ``motion.names``); :class:`~diffkin.errors.ConventionError` listing the skeletons when none is."""
    have = set(names)
    for key, roles in SKELETONS.items():
        if set(roles.values()) <= have:
            return key
    raise ConventionError(f"the clip's joints {sorted(have)[:8]}... match none of the skeletons "
                          f"{sorted(SKELETONS)}; write a Mapping for them")

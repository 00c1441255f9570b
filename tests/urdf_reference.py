"""An independent numpy reference forward kinematics for URDF trees, written for the tests (no diffkin).

It reads the URDF with ``xml.etree`` (from bytes, so files with an ``<?xml ... encoding="utf-8"?>``
declaration parse too), walks from the end link up through the parent joints to the root (or to a given root
link), and multiplies, root first,

    T = prod_j  Origin_j(xyz, rpy) @ Motion_j(q_j)

with Origin = Trans(xyz) Rz(yaw) Ry(pitch) Rx(roll) (URDF's fixed-axis roll-pitch-yaw), Motion a rotation by
Rodrigues' formula about the normalised axis (revolute, continuous), a translation along the normalised axis
(prismatic) or the identity (fixed). A joint with a ``<mimic joint=L multiplier=m offset=o>`` element (and a
moving type) takes q = m * q_L + o, m = 1 and o = 0 when absent; it is never an independent variable.

The reference itself is checked against pytorch-kinematics in tests/test_urdf_models.py.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np

MOVING = ("revolute", "continuous", "prismatic")


@dataclass(frozen=True)
class RefJoint:
    name: str
    type: str
    parent: str
    child: str
    xyz: tuple[float, float, float]
    rpy: tuple[float, float, float]
    axis: tuple[float, float, float]
    mimic: tuple[str, float, float] | None  # (leader, multiplier, offset)
    limits: tuple[float, float] | None  # (lower, upper); None for continuous or when absent

    @property
    def moving(self) -> bool:
        return self.type in MOVING

    @property
    def independent(self) -> bool:
        return self.moving and self.mimic is None


def _floats(text: str | None, default: tuple[float, ...]) -> tuple[float, ...]:
    if text is None:
        return default
    vals = tuple(float(v) for v in text.split())
    assert len(vals) == len(default), text
    return vals


def _read_bytes(source) -> bytes:
    if isinstance(source, bytes):
        return source
    if isinstance(source, Path):
        return source.read_bytes()
    if isinstance(source, str) and source.lstrip().startswith("<"):
        return source.encode("utf-8")
    return Path(source).read_bytes()


def rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def origin_matrix(xyz, rpy) -> np.ndarray:
    """Trans(xyz) Rz(yaw) Ry(pitch) Rx(roll)."""
    T = np.eye(4)
    T[:3, :3] = rot_z(rpy[2]) @ rot_y(rpy[1]) @ rot_x(rpy[0])
    T[:3, 3] = xyz
    return T


def rodrigues(axis, angle: float) -> np.ndarray:
    k = np.asarray(axis, dtype=np.float64)
    k = k / np.linalg.norm(k)
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(angle) * K + (1.0 - math.cos(angle)) * (K @ K)


def motion_matrix(joint: RefJoint, q: float) -> np.ndarray:
    T = np.eye(4)
    if joint.type in ("revolute", "continuous"):
        T[:3, :3] = rodrigues(joint.axis, q)
    elif joint.type == "prismatic":
        k = np.asarray(joint.axis, dtype=np.float64)
        T[:3, 3] = q * k / np.linalg.norm(k)
    elif joint.type != "fixed":
        raise ValueError(f"reference: joint type {joint.type!r} ({joint.name}) not supported")
    return T


class ReferenceTree:
    """A URDF kinematic tree: ``fk({joint: q}, end_link, root_link=None) -> (4, 4)`` in float64."""

    def __init__(self, source):
        root = ET.fromstring(_read_bytes(source))
        self.name = root.get("name")
        self.links: list[str] = [link.get("name") for link in root.findall("link")]
        self.joints: dict[str, RefJoint] = {}
        self.parent_joint: dict[str, str] = {}  # child link -> joint name
        for j in root.findall("joint"):
            origin = j.find("origin")
            axis = j.find("axis")
            mimic = j.find("mimic")
            limit = j.find("limit")
            jtype = j.get("type")
            limits = None
            if jtype in ("revolute", "prismatic") and limit is not None and limit.get("lower") is not None:
                limits = (float(limit.get("lower")), float(limit.get("upper")))
            joint = RefJoint(
                name=j.get("name"),
                type=jtype,
                parent=j.find("parent").get("link"),
                child=j.find("child").get("link"),
                xyz=_floats(None if origin is None else origin.get("xyz"), (0.0, 0.0, 0.0)),
                rpy=_floats(None if origin is None else origin.get("rpy"), (0.0, 0.0, 0.0)),
                axis=_floats(None if axis is None else axis.get("xyz"), (1.0, 0.0, 0.0)),
                mimic=None if mimic is None or jtype not in MOVING else (
                    mimic.get("joint"), float(mimic.get("multiplier", 1.0)), float(mimic.get("offset", 0.0))),
                limits=limits,
            )
            assert joint.name not in self.joints, joint.name
            assert joint.child not in self.parent_joint, joint.child
            self.joints[joint.name] = joint
            self.parent_joint[joint.child] = joint.name
        roots = [link for link in self.links if link not in self.parent_joint]
        assert len(roots) == 1, roots
        self.root = roots[0]

    # ---- structure -------------------------------------------------------------------------------------
    def path_joints(self, end_link: str, root_link: str | None = None) -> list[str]:
        """All joints (fixed ones included) from the root (or root_link) down to end_link, root first."""
        if end_link not in self.links:
            raise KeyError(end_link)
        path = []
        link = end_link
        while link != (root_link or self.root):
            if link not in self.parent_joint:
                raise ValueError(f"{root_link!r} is not an ancestor of {end_link!r}")
            jname = self.parent_joint[link]
            path.append(jname)
            link = self.joints[jname].parent
        return path[::-1]

    def moving_path_joints(self, end_link: str, root_link: str | None = None) -> list[str]:
        return [j for j in self.path_joints(end_link, root_link) if self.joints[j].moving]

    def leader(self, jname: str) -> str:
        """The independent joint that drives jname (itself when it has no mimic)."""
        seen = set()
        while self.joints[jname].mimic is not None:
            assert jname not in seen, "mimic cycle"
            seen.add(jname)
            jname = self.joints[jname].mimic[0]
        return jname

    def variables(self, end_links, root_link: str | None = None) -> set[str]:
        """The independent joints the pose of any of end_links depends on (mimic leaders included)."""
        if isinstance(end_links, str):
            end_links = [end_links]
        return {self.leader(j) for e in end_links for j in self.moving_path_joints(e, root_link)}

    def ancestors(self, end_link: str, root_link: str | None = None) -> set[str]:
        """Independent joints whose motion moves end_link (through a path joint or a mimic follower on it)."""
        return self.variables(end_link, root_link)

    def limits(self, jname: str) -> tuple[float, float] | None:
        return self.joints[jname].limits

    # ---- kinematics ------------------------------------------------------------------------------------
    def joint_value(self, jname: str, q: dict[str, float]) -> float:
        joint = self.joints[jname]
        if joint.mimic is None:
            return float(q[jname])
        leader, mult, off = joint.mimic
        return mult * self.joint_value(leader, q) + off

    def fk(self, q: dict[str, float], end_link: str, root_link: str | None = None) -> np.ndarray:
        """Pose (4, 4) of end_link in the frame of root_link (default: the tree root)."""
        T = np.eye(4)
        for jname in self.path_joints(end_link, root_link):
            joint = self.joints[jname]
            T = T @ origin_matrix(joint.xyz, joint.rpy)
            if joint.moving:
                T = T @ motion_matrix(joint, self.joint_value(jname, q))
        return T

    def random_q(self, names, rng: np.random.Generator, margin: float = 0.05) -> dict[str, float]:
        """Uniform values within each joint's limits (shrunk by margin), in [-pi, pi] when unlimited."""
        q = {}
        for name in names:
            lim = self.limits(name)
            lo, hi = lim if lim is not None else (-math.pi, math.pi)
            q[name] = float(rng.uniform(lo + margin * (hi - lo), hi - margin * (hi - lo)))
        return q

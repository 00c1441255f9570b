"""A BVH reader: the HIERARCHY (offsets, channels, End Sites) and the MOTION frames, forward kinematics of
the skeleton with :mod:`diffkin.rotations`, converted to metres and z up.

Conventions (Biovision's, as every exporter of the CMU conversions writes them):

* each joint's local rotation is the product of its rotation channels *in the order the CHANNELS line
  lists them*, ``R = R_a(θ1) R_b(θ2) R_c(θ3)`` (intrinsic: ``Zrotation Xrotation Yrotation`` is
  ``Rz Rx Ry``), angles in degrees;
* a joint's position is its parent's position plus the parent's world rotation times (its OFFSET plus
  its position channels, if it has any); the root's position channels are its world position;
* the frame rate is 1 / Frame Time, rounded to the nearest integer when within 0.1 % of it (Frame Time
  is written with about 7 digits: ``.0083333`` is 120 fps);
* the returned Motion has ``parents`` (the parent index of each joint, -1 for the root);
* an ``End Site`` becomes a joint named ``<parent>_end`` (no channels), so toe and head tips are kept.

Units: BVH stores no unit. ``scale`` multiplies every length; ``scale=None`` picks, from the rest pose's
height h (top of the skeleton minus its lowest point, offsets only), the unit of :data:`UNITS` that makes
h·scale closest to 1.7 m (a ratio test on log h): metres, the CMU skeleton's unit, inches, centimetres or
millimetres. The CMU database's unit is 1/0.45 inch = 0.05644 m (its ASF files' ``length 0.45`` and
mocap.cs.cmu.edu's FAQ); the cgspeed BVH conversions keep it. Its rest heights (about 30 units) and those
of inch files (about 67) are a factor 2.2 apart, so the choice is unambiguous for adult skeletons; give
``scale`` for anything else.

Axes: BVH is y up. Positions are turned to z up by the rotation of +90° about x,
``(x, y, z) -> (x, -z, y)`` (right-handed, nothing mirrored); joint frames are premultiplied by the same
rotation.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ..errors import ModelError
from ..rotations import rot_x, rot_y, rot_z
from ..validation import check_number
from .motion import Motion

__all__ = ["CMU_UNIT", "UNITS", "load_bvh"]

#: metres per unit of the CMU motion-capture skeleton: 1/0.45 inch.
CMU_UNIT = 0.0254 / 0.45
#: the units ``load_bvh(scale=None)`` chooses among (metres per file unit)
UNITS = {"m": 1.0, "cmu": CMU_UNIT, "inch": 0.0254, "cm": 0.01, "mm": 0.001}
_ROT = {"x": rot_x, "y": rot_y, "z": rot_z}
_TARGET_HEIGHT = 1.7


@dataclass
class _Joint:
    name: str
    parent: int
    offset: list[float]
    channels: list[str] = field(default_factory=list)


def _parse(text: str, where: str):
    tokens = re.findall(r"[^\s{}]+|[{}]", text)
    joints: list[_Joint] = []
    stack: list[int] = []
    i = 0

    def fail(msg):
        raise ModelError(f"{where}: {msg}")

    def number(k):
        try:
            return float(tokens[k])
        except (IndexError, ValueError):
            fail(f"expected a number, got {tokens[k] if k < len(tokens) else 'the end of the file'!r}")

    if not tokens or tokens[0].upper() != "HIERARCHY":
        fail("not a BVH file: it does not start with HIERARCHY")
    i = 1
    pending = None
    while i < len(tokens):
        tok = tokens[i]
        up = tok.upper()
        if up in ("ROOT", "JOINT"):
            if up == "ROOT" and joints:
                fail("more than one ROOT (one skeleton per file is supported)")
            pending = _Joint(tokens[i + 1], stack[-1] if stack else -1, [0.0, 0.0, 0.0])
            i += 2
        elif up == "END":  # End Site
            parent = stack[-1] if stack else fail("End Site outside a joint")
            pending = _Joint(f"{joints[parent].name}_end", parent, [0.0, 0.0, 0.0])
            i += 2
        elif tok == "{":
            if pending is None:
                fail("'{' without a ROOT, JOINT or End Site")
            joints.append(pending)
            stack.append(len(joints) - 1)
            pending = None
            i += 1
        elif tok == "}":
            if not stack:
                fail("unbalanced '}'")
            stack.pop()
            i += 1
        elif up == "OFFSET":
            joints[stack[-1]].offset = [number(i + 1), number(i + 2), number(i + 3)]
            i += 4
        elif up == "CHANNELS":
            n = int(number(i + 1))
            chans = [c.lower() for c in tokens[i + 2:i + 2 + n]]
            for c in chans:
                if c not in {f"{a}{k}" for a in "xyz" for k in ("position", "rotation")}:
                    fail(f"unknown channel {c!r} of joint {joints[stack[-1]].name!r}")
            joints[stack[-1]].channels = chans
            i += 2 + n
        elif up == "MOTION":
            if stack:
                fail("MOTION before the HIERARCHY's braces close")
            break
        else:
            fail(f"unexpected token {tok!r} in the HIERARCHY")
    else:
        fail("no MOTION section")
    if not joints:
        fail("no joints in the HIERARCHY")
    # MOTION: "Frames: N", "Frame Time: dt", then N rows
    rest = text[text.upper().index("MOTION") + len("MOTION"):]
    m = re.search(r"Frames:\s*(\d+)\s*Frame\s+Time:\s*([-+0-9.eE]+)", rest, re.IGNORECASE)
    if m is None:
        fail("MOTION without 'Frames:' and 'Frame Time:' lines")
    n_frames, dt = int(m.group(1)), float(m.group(2))
    values = np.array(rest[m.end():].split(), dtype=np.float64) if rest[m.end():].strip() else np.zeros(0)
    width = sum(len(j.channels) for j in joints)
    if n_frames < 1 or values.size != n_frames * width:
        fail(f"MOTION declares {n_frames} frames of {width} channels ({n_frames * width} numbers), the file "
             f"holds {values.size}")
    if not dt > 0:
        fail(f"Frame Time must be > 0, got {dt}")
    return joints, values.reshape(n_frames, width), dt


def _rest_height(joints: list[_Joint]) -> float:
    y = []
    for j in joints:
        y.append(j.offset[1] + (y[j.parent] if j.parent >= 0 else 0.0))
    return max(y) - min(y)


def _choose_scale(joints: list[_Joint], where: str) -> float:
    h = _rest_height(joints)
    if not h > 0:
        raise ModelError(f"{where}: the rest pose has no height (all offsets flat); give scale= (metres per "
                         "file unit)")
    return min(UNITS.values(), key=lambda s: abs(math.log(h * s / _TARGET_HEIGHT)))


def _forward_kinematics(joints: list[_Joint], frames: torch.Tensor):
    """World positions (T, J, 3) and rotations (T, J, 3, 3) in the file's axes and units."""
    T = frames.shape[0]
    dtype = frames.dtype
    pos, rot = [], []
    col = 0
    eye = torch.eye(3, dtype=dtype).expand(T, 3, 3)
    for j in joints:
        R = eye
        t = torch.tensor(j.offset, dtype=dtype).expand(T, 3)
        for c in j.channels:
            v = frames[:, col]
            col += 1
            axis = c[0]
            if c.endswith("position"):
                t = t + torch.nn.functional.one_hot(torch.tensor("xyz".index(axis)), 3).to(dtype) * v[:, None]
            else:
                R = R @ _ROT[axis](torch.deg2rad(v))
        if j.parent < 0:
            pos.append(t)
            rot.append(R)
        else:
            Rp = rot[j.parent]
            pos.append(pos[j.parent] + (Rp @ t.unsqueeze(-1)).squeeze(-1))
            rot.append(Rp @ R)
    return torch.stack(pos, 1), torch.stack(rot, 1)


def load_bvh(path, *, scale: float | None = None, dtype: torch.dtype = torch.float64) -> Motion:
    """A BVH file as a one-clip :class:`~diffkin.retarget.Motion` (B = 1) in metres, z up, with joint
    orientations. See the module doc for the channel order, units (``scale``: metres per file unit,
    None: chosen from the rest pose's height) and axes.

    Raises :class:`~diffkin.errors.ModelError` naming the file for a malformed file (a missing section,
    an unknown channel, a frame count that does not match the numbers).
    """
    path = Path(path)
    if not path.is_file():
        raise ModelError(f"BVH file not found: {str(path)!r}")
    joints, values, dt = _parse(path.read_text(encoding="utf-8", errors="replace"), str(path))
    s = _choose_scale(joints, str(path)) if scale is None else check_number(scale, "scale", unit=" m/unit")
    frames = torch.as_tensor(values, dtype=torch.float64)
    p, R = _forward_kinematics(joints, frames)
    C = rot_x(torch.tensor(math.pi / 2, dtype=torch.float64))  # y up -> z up: (x, y, z) -> (x, -z, y)
    C = torch.where(C.abs() < 1e-12, torch.zeros_like(C), C)
    p = (p * s) @ C.T
    R = C @ R
    fps = 1.0 / dt
    if abs(fps - round(fps)) < 1e-3 * fps:  # "Frame Time: .0083333" is 120 fps written with 7 digits
        fps = float(round(fps))
    motion = Motion(p.to(dtype).unsqueeze(0), [j.name for j in joints], fps, R.to(dtype).unsqueeze(0))
    motion.parents = [j.parent for j in joints]  # the skeleton's tree: each joint's parent, -1 the root
    return motion

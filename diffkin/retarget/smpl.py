"""SMPL / SMPL-H / SMPL-X joint arrays from ``.npz`` files (no body model needed).

The file holds joint *positions* (what a body model's forward pass or AMASS-style preprocessing
writes), not pose parameters: key ``"joints"`` (T, J, 3) or (B, T, J, 3) in metres, and the frame rate
under ``"fps"`` or ``"mocap_framerate"`` (AMASS's name) unless ``fps=`` is given. The joint names follow
from J: 22 (SMPL body), 24 (SMPL), 52 (SMPL-H) or 55 (SMPL-X), in the body models' order
(:data:`SMPLX_JOINT_NAMES`); other counts need ``names=``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from ..errors import ModelError
from ..validation import check_number
from .motion import Motion

__all__ = ["SMPL_JOINT_NAMES", "SMPLX_JOINT_NAMES", "load_smpl"]

_BODY = ["pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2", "left_ankle",
         "right_ankle", "spine3", "left_foot", "right_foot", "neck", "left_collar", "right_collar", "head",
         "left_shoulder", "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist"]
_FINGERS = [f"{f}{k}" for f in ("index", "middle", "pinky", "ring", "thumb") for k in (1, 2, 3)]
_HANDS = [f"left_{f}" for f in _FINGERS] + [f"right_{f}" for f in _FINGERS]
#: the 24 joints of SMPL, in its order
SMPL_JOINT_NAMES = [*_BODY, "left_hand", "right_hand"]
#: the 55 joints of SMPL-X, in its order (the first 22 are SMPL's body joints; SMPL-H is body + hands)
SMPLX_JOINT_NAMES = [*_BODY, "jaw", "left_eye_smplhf", "right_eye_smplhf", *_HANDS]
_BY_COUNT = {22: _BODY, 24: SMPL_JOINT_NAMES, 52: [*_BODY, *_HANDS], 55: SMPLX_JOINT_NAMES}


def load_smpl(path, *, fps: float | None = None, names=None, up: str = "z", key: str = "joints",
              dtype: torch.dtype = torch.float64) -> Motion:
    """A :class:`~diffkin.retarget.Motion` of the joint positions in an ``.npz`` file (see the module doc).

    Args:
        path: the ``.npz`` file.
        fps: frames per second; None reads ``"fps"`` or ``"mocap_framerate"`` from the file.
        names: joint names, needed when J is not 22, 24, 52 or 55.
        up: the file's up axis: ``"z"`` (AMASS) or ``"y"`` (a body model's own frame); y-up positions are
            turned by +90° about x, ``(x, y, z) -> (x, -z, y)``, as :func:`~diffkin.retarget.load_bvh` does.
        key: the array's key.

    Raises :class:`~diffkin.errors.ModelError` naming the file for a missing key, an unknown joint count
    or up axis; the :class:`~diffkin.retarget.Motion` checks (NaN frames, fps <= 0, shapes) apply.
    """
    path = Path(path)
    if not path.is_file():
        raise ModelError(f"SMPL joint file not found: {str(path)!r}")
    with np.load(path, allow_pickle=False) as data:
        if key not in data.files:
            raise ModelError(f"{path}: no array {key!r} (joint positions (T, J, 3)); the file holds "
                             f"{sorted(data.files)}")
        joints = np.asarray(data[key], dtype=np.float64)
        if fps is None:
            for k in ("fps", "mocap_framerate"):
                if k in data.files:
                    fps = float(np.asarray(data[k]).reshape(-1)[0])
                    break
            else:
                raise ModelError(f"{path}: no frame rate ('fps' or 'mocap_framerate'); give fps=")
    fps = check_number(fps, "fps", unit=" frames per second")
    J = joints.shape[-2] if joints.ndim >= 2 else 0
    if names is None:
        if J not in _BY_COUNT:
            raise ModelError(f"{path}: {J} joints is not SMPL's body (22), SMPL (24), SMPL-H (52) or SMPL-X "
                             "(55); give names=")
        names = _BY_COUNT[J]
    if up not in ("z", "y"):
        raise ModelError(f"up must be 'z' or 'y', got {up!r}")
    p = torch.as_tensor(joints, dtype=dtype)
    if up == "y" and p.shape[-1] == 3:
        p = torch.stack((p[..., 0], -p[..., 2], p[..., 1]), -1)
    return Motion(p, names, fps)

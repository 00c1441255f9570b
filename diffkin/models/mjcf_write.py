"""Writing an MJCF chain's geometry back into its source text (:meth:`MJCFChain.to_mjcf`), by text surgery.

The chain's parameters are MuJoCo's compiled values: a body's pose relative to its parent body, after the
enclosing ``<frame>`` s. For an element whose parameters changed, the new pose in the element's own
coordinates is ``T_local_new = T_local_old · T_compiled_old⁻¹ · T_compiled_new`` (the frames are fixed), with
``T_local_old`` from MuJoCo's parser (``MjSpec``: ``pos`` and the orientation in whichever form the file
uses, resolved with the file's ``<compiler angle eulerseq>``). The element's ``pos`` and orientation
attributes are replaced by ``pos`` and ``quat``; every other byte of the file stays as it was.
"""

from __future__ import annotations

import re
from pathlib import Path

import torch
from torch import Tensor

from ..errors import ModelError, require
from ..rotations import _matrix_to_quaternion, _quaternion_to_matrix
from ..transforms import _make_transform, _transform_inverse

__all__ = ["write_mjcf"]

_ORIENTATION = ("quat", "euler", "axisangle", "xyaxes", "zaxis")
_TAG = re.compile(r"<(body|joint|site)\b((?:[^>\"']|\"[^\"]*\"|'[^']*')*?)(/?)>", re.S)
_NAME = re.compile(r"\bname\s*=\s*([\"'])(.*?)\1", re.S)
_COMMENT = re.compile(r"<!--.*?-->", re.S)


def _pose(pos: Tensor, quat: Tensor) -> Tensor:
    return _make_transform(_quaternion_to_matrix(quat / quat.norm()), pos)


def _local_pose(mujoco, spec, element) -> Tensor:
    """The element's pose in its own coordinates (``pos`` and orientation as written), float64."""
    alt = element.alt
    if alt.type == mujoco.mjtOrientation.mjORIENTATION_QUAT:
        quat = list(element.quat)
    else:
        quat = spec.resolve_orientation(spec.compiler.degree, spec.compiler.eulerseq, alt)
    return _pose(torch.tensor(list(element.pos), dtype=torch.float64),
                 torch.tensor(list(quat), dtype=torch.float64))


def _fmt(values) -> str:
    return " ".join(f"{float(v):.12g}" for v in values)


def _changed(a: Tensor, b: Tensor) -> bool:
    return not torch.equal(a, b)


def _pose_edits(mujoco, spec, chain, cur: dict, kind: str, names: list[str], edits: dict) -> None:
    """``edits[(tag, name)]`` for the bodies (``kind="body"``) or sites whose pose parameters changed."""
    pos0, quat0 = chain._compiled0[f"{kind}_pos"], chain._compiled0[f"{kind}_quat"]
    pos, quat = cur[f"{kind}_pos"], cur[f"{kind}_quat"]
    for i, name in enumerate(names):
        if not (_changed(pos[i], pos0[i]) or _changed(quat[i], quat0[i])):
            continue
        element = (spec.body if kind == "body" else spec.site)(name) if name else None
        if element is None:
            raise ModelError(f"to_mjcf: {kind} {i} of the chain has no name in the file: it cannot be "
                             "written")
        T_old, T_new = _pose(pos0[i], quat0[i]), _pose(pos[i], quat[i])
        T = _local_pose(mujoco, spec, element) @ _transform_inverse(T_old) @ T_new
        q = _matrix_to_quaternion(T[:3, :3])
        edits[(kind, name)] = {"pos": _fmt(T[:3, 3]), "quat": _fmt(q)}


def _joint_edits(chain, cur: dict, edits: dict) -> None:
    anchors, axes = chain._joint_rows
    for rows, key, attr in ((anchors, "joint_pos", "pos"), (axes, "joint_axis", "axis")):
        for i, name in enumerate(rows):
            if _changed(cur[key][i], chain._compiled0[key][i]):
                if not name:
                    raise ModelError(f"to_mjcf: joint row {i} has no name in the file: it cannot be written")
                edits.setdefault(("joint", name), {})[attr] = _fmt(cur[key][i])


def _rewrite(text: str, edits: dict) -> str:
    comments = [m.span() for m in _COMMENT.finditer(text)]
    out, last, done = [], 0, set()
    for m in _TAG.finditer(text):
        if any(a <= m.start() < b for a, b in comments):
            continue
        tag, attrs, close = m.group(1), m.group(2), m.group(3)
        name = _NAME.search(attrs)
        key = (tag, name.group(2)) if name else None
        if key not in edits:
            continue
        new = edits[key]
        drop = set(new) | (set(_ORIENTATION) if "quat" in new else set())
        kept = re.sub(r"\s+(" + "|".join(drop) + r")\s*=\s*([\"']).*?\2", "", attrs, flags=re.S)
        added = "".join(f' {k}="{v}"' for k, v in new.items())
        out += [text[last:m.start()], f"<{tag}{kept}{added}{close}>"]
        last = m.end()
        done.add(key)
    missing = sorted(set(edits) - done)
    if missing:
        raise ModelError(f"to_mjcf: {', '.join(f'{t} {n!r}' for t, n in missing)} not found in the main file "
                         "(defined in an <include>?)")
    return "".join(out) + text[last:]


def write_mjcf(chain, path=None) -> str:
    """See :meth:`diffkin.models.mjcf.MJCFChain.to_mjcf`."""
    mujoco = require("mujoco", "mjcf", "MJCF models")
    if chain.base is not None or chain.tool is not None:
        raise ModelError("to_mjcf: the chain has a base or tool transform, which an MJCF has no place for")
    src = chain.source_path
    spec = mujoco.MjSpec.from_file(src) if src else mujoco.MjSpec.from_string(chain.source_text)
    names = ("body_pos", "body_quat", "joint_pos", "joint_axis", "site_pos", "site_quat")
    cur = {k: getattr(chain, k).detach().double().cpu() for k in names}
    edits: dict = {}
    _pose_edits(mujoco, spec, chain, cur, "body", chain.body_names, edits)
    _pose_edits(mujoco, spec, chain, cur, "site", chain.site_names, edits)
    _joint_edits(chain, cur, edits)
    text = _rewrite(chain.source_text, edits)
    if path is not None:
        Path(path).write_text(text, encoding="utf-8")
    return text

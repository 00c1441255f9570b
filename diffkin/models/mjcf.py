"""MuJoCo (MJCF) models as kinematic chains: read by MuJoCo's own compiler, learnable like a URDF chain.

:func:`from_mjcf` compiles the file with the ``mujoco`` package (the ``mjcf`` extra), so default classes and
``childclass``, ``<include>``, ``<compiler angle/eulerseq/autolimits>``, every orientation form (``quat``,
``euler``, ``axisangle``, ``xyaxes``, ``zaxis``), ``<frame>``, joint ``pos``/``axis``/``ref`` and several
joints in one body come out exactly as in MuJoCo. Files whose meshes, textures or height fields are absent
still load: kinematics needs none of them, so mesh geoms become small spheres and file assets are dropped
before compiling (:func:`compile_mjcf`).

The chain is the tree of bodies between the root (the world, or ``root_link``) and the end links (bodies
or sites), with MuJoCo's frame rule (``mj_kinematics``): a body's frame is its parent's times its
``pos``/``quat``, then each of its joints in order. A hinge rotates about its axis through its ``pos`` by
q − ref; a slide moves along its axis by q − ref; a ball rotates by its quaternion about its ``pos``; a free
joint sets the body's position and orientation in the world directly. In the kernels
(:mod:`diffkin.kernels.configuration`) a hinge is Pre = (bodies) · Trans(pos) · S, Rz, Post = Sᵀ ·
Trans(−pos), with S taking e_z to the axis; a free joint is three translations along the world axes and a
ball motion.

q is ``(..., nq)`` in MuJoCo's qpos order for the chain's joints (``joint_names``), velocities and Jacobian
columns ``(..., nv)`` in its qvel order: for ball and free joints the angular velocity in the body frame and
(free) the linear velocity in the world frame, so :meth:`MJCFChain.geometric_jacobian` equals
``mj_jacBody`` / ``mj_jacSite`` on the chain's columns. Linear ``<equality><joint polycoef>`` couplings become
mimic joints; other equality constraints (connect, weld: closed loops) are named in a warning and not
enforced.
"""

from __future__ import annotations

import math
import os
import re
import warnings
from pathlib import Path

import torch
from torch import Tensor

from .._numerics import stable_norm
from ..errors import ModelError, require
from ..kernels.configuration import JointKind, joint_kind, mjcf_kind
from ..kernels.joints import axis_alignment
from ..rotations import _quaternion_to_matrix
from ..transforms import _make_transform
from ..validation import check_device, check_end_links, tensors
from .description import BodyInertia, FrameSpec, TreeChain, TreeDescription, kind_frames

__all__ = ["MJCFChain", "from_mjcf", "compile_mjcf"]

_STAND_IN_RADIUS = 0.01  # a mesh geom becomes a sphere this big: positive, so inferred masses stay positive


def _mujoco():
    return require("mujoco", "mjcf", "MJCF models")


def _strip_assets(spec) -> None:
    """Mesh / height-field / SDF geoms become small spheres (kept, so pairs and sensors naming them still
    resolve); mesh, height-field and skin assets and file textures are deleted. Body frames do not depend
    on geoms."""
    mujoco = _mujoco()
    file_types = (mujoco.mjtGeom.mjGEOM_MESH, mujoco.mjtGeom.mjGEOM_HFIELD, mujoco.mjtGeom.mjGEOM_SDF)
    for geom in spec.geoms:
        if geom.type in file_types:
            geom.type = mujoco.mjtGeom.mjGEOM_SPHERE
            geom.meshname = ""
            geom.hfieldname = ""
            geom.size = [_STAND_IN_RADIUS, 0.0, 0.0]
    for group in (spec.meshes, spec.hfields, spec.skins):
        for item in list(group):
            spec.delete(item)
    for texture in list(spec.textures):
        if texture.file or any(texture.cubefiles):
            spec.delete(texture)
    for material in spec.materials:
        material.textures = [""] * len(material.textures)


def _decode(data: bytes, where: str) -> str:
    """MJCF bytes as text: MuJoCo reads its XML as UTF-8 (a BOM is allowed); anything else is a
    :class:`~diffkin.errors.ModelError` naming the source and the first bad byte."""
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise ModelError(f"{where}: not UTF-8 text (byte 0x{data[e.start]:02x} at offset {e.start}); MuJoCo "
                         "reads MJCF as UTF-8: save the file as UTF-8") from None


_FIRST_TAG = re.compile(r"\A(?:\s+|<\?.*?\?>|<!--.*?-->|<!DOCTYPE[^>]*>)*<\s*([A-Za-z_][\w.:-]*)", re.S)


def _refuse_urdf(text: str, where: str) -> None:
    """A URDF (root element ``<robot>``) given as an MJCF: MuJoCo would compile it, merging its fixed links
    away (a ``tool0`` end link would then not exist); the error points to the URDF reader."""
    m = _FIRST_TAG.match(text)
    if m and m.group(1) == "robot":
        raise ModelError(f"{where} is a URDF (root element <robot>), not an MJCF (<mujoco>): load it with "
                         "diffkin.models.from_urdf(source, end_link) (RobotCollision.from_urdf for its "
                         "geoms)")


def _read_source(source) -> tuple[str, str | None]:
    """``(xml text, path or None)`` of a path, XML text or bytes: UTF-8 MJCF, not a URDF."""
    if isinstance(source, bytes | bytearray | memoryview):
        text, path = _decode(bytes(source), "<MJCF bytes>"), None
    elif isinstance(source, os.PathLike) or (isinstance(source, str) and not source.lstrip().startswith("<")):
        file = Path(source)
        if not file.is_file():
            raise ModelError(f"MJCF file not found: {str(file)!r}")
        text, path = _decode(file.read_bytes(), str(file)), str(file)
    elif isinstance(source, str):
        text, path = source, None
    else:
        raise ModelError(f"expected an MJCF path, XML text or bytes, got {type(source).__name__}")
    _refuse_urdf(text, path or "the MJCF text")
    return text, path


def compile_mjcf(source):
    """``(mujoco.MjModel, xml text, path or None)`` of an MJCF path, XML text or bytes, compiled by MuJoCo
    without the asset files it names (see the module doc). ``<include>`` files are found next to the file
    (for XML text: relative to the working directory). MuJoCo's errors become a
    :class:`~diffkin.errors.ModelError` naming the source."""
    mujoco = _mujoco()
    text, path = _read_source(source)
    where = path or "<MJCF text>"
    try:
        spec = mujoco.MjSpec.from_file(path) if path else mujoco.MjSpec.from_string(text)
        _strip_assets(spec)
        model = spec.compile()
    except (ValueError, mujoco.FatalError) as exc:
        raise ModelError(f"{where}: MuJoCo could not compile the model: {exc}") from None
    return model, text, path


def _name(model, kind, i: int) -> str:
    return _mujoco().mj_id2name(model, kind, i) or ""


def _resolve_end(model, name: str) -> tuple[int, int | None]:
    """``(body id, site id or None)`` of an end-link name: a body first, else a site."""
    mujoco = _mujoco()
    if not isinstance(name, str):
        raise ModelError(f"end_link: expected a body or site name (str), got {type(name).__name__}")
    b = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, name)
    if b >= 0:
        return b, None
    s = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, name)
    if s >= 0:
        return int(model.site_bodyid[s]), s
    bodies = [_name(model, mujoco.mjtObj.mjOBJ_BODY, i) for i in range(model.nbody)]
    raise ModelError(f"end_link {name!r} is neither a body nor a site of the model (bodies: {bodies[1:12]}"
                     f"{' ...' if len(bodies) > 12 else ''})")


class _Builder:
    """Walks the bodies of the paths in MuJoCo's order and lays out the frames of the tree product."""

    def __init__(self, model, path_bodies: list[int], root: int):
        self.m = model
        self.parent = {b: int(model.body_parentid[b]) for b in path_bodies}
        self.frames: list[dict] = []  # kind, parent, pre tokens, post tokens, joint, q slot
        self.last_frame = {root: -1}  # body -> the last frame at or above it
        self.pending = {root: []}  # body -> fixed body tokens since that frame
        self.bodies: list[int] = []  # learnable body transforms (rows of body_pos / body_quat)
        self.joints: list[int] = []  # chain joints in qpos order
        self.axis_joints: list[int] = []  # hinge and slide joints (rows of joint_axis)
        self.anchor_joints: list[int] = []  # hinge, slide and ball joints (rows of joint_pos)
        for b in path_bodies:
            self._body(b)

    def _body(self, b: int) -> None:
        mujoco = _mujoco()
        p = self.parent[b]
        frame, tokens = self.last_frame[p], list(self.pending[p])
        nj, adr = int(self.m.body_jntnum[b]), int(self.m.body_jntadr[b])
        types = [int(self.m.jnt_type[adr + k]) for k in range(nj)]
        if mujoco.mjtJoint.mjJNT_FREE not in types:  # a free joint overrides the body's own pose
            self.bodies.append(b)
            tokens.append(("B", len(self.bodies) - 1))
        for k in range(nj):
            j, t = adr + k, types[k]
            self.joints.append(j)
            kind = _kind(self.m, j)
            pre, post = list(tokens), []
            if t != mujoco.mjtJoint.mjJNT_FREE:  # MuJoCo places every joint but a free one at its pos
                self.anchor_joints.append(j)
                anchor = len(self.anchor_joints) - 1
                pre, post = pre + [("J", anchor)], [("Jn", anchor)]
            if kind.has_axis:
                self.axis_joints.append(j)
                h = len(self.axis_joints) - 1
                pre, post = pre + [("A", h)], [("At", h)] + post
            for spec in kind_frames(kind, frame, len(self.frames), 0, pre, post):
                self.frames.append({"kind": spec.motion, "parent": spec.parent, "pre": list(spec.pre),
                                    "post": list(spec.post), "joint": j, "qoff": spec.q_index})
            frame, tokens = len(self.frames) - 1, []
        self.last_frame[b], self.pending[b] = frame, tokens


def _kind(model, j: int) -> JointKind:
    """The joint kind of MuJoCo joint ``j`` (the ``mjcf`` column of the kinds table; a hinge is revolute
    where limited, else continuous)."""
    name = _mujoco().mjtJoint(int(model.jnt_type[j])).name[len("mjJNT_"):].lower()
    return mjcf_kind(name, bool(model.jnt_limited[j]))


def _couplings(model, chain_joints: list[int]) -> tuple[dict[int, tuple[int, float, float]], list[str]]:
    """Linear joint equalities among the chain's joints: follower -> (leader, m, b) with
    q_follower = m q_leader + b, the leader an independent joint (chains j3 -> j2 -> j1 composed into
    j3 -> j1); and the names of the equality constraints that are not enforced. Two active equalities
    on one follower, or couplings in a cycle, are a :class:`~diffkin.errors.ModelError`."""
    mujoco = _mujoco()
    direct, by, ignored = {}, {}, []
    inside = set(chain_joints)
    jname = lambda j: _name(model, mujoco.mjtObj.mjOBJ_JOINT, j) or f"joint {j}"  # noqa: E731
    for e in range(model.neq):
        name = _name(model, mujoco.mjtObj.mjOBJ_EQUALITY, e) or f"equality {e}"
        etype = int(model.eq_type[e])
        if etype != mujoco.mjtEq.mjEQ_JOINT:
            ignored.append(f"{name} ({mujoco.mjtEq(etype).name[5:].lower()})")
            continue
        j1, j2 = int(model.eq_obj1id[e]), int(model.eq_obj2id[e])
        if j1 not in inside:
            continue
        c = [float(x) for x in model.eq_data[e, :5]]
        if any(abs(x) > 0 for x in c[2:]) or (j2 >= 0 and j2 not in inside) or not model.eq_active0[e]:
            why = "polynomial" if any(c[2:]) else "inactive" if not model.eq_active0[e] else \
                "leader outside the chain"
            ignored.append(f"{name} (joint, {why})")
            continue
        if j2 < 0:  # joint1 held at a constant
            ignored.append(f"{name} (joint held fixed)")
            continue
        if j1 in direct:  # MuJoCo would enforce both (over-constrained); keeping one would be a silent choice
            raise ModelError(f"joint {jname(j1)!r} follows two joint equalities ({by[j1]!r} and {name!r}); "
                             "a joint can follow one leader: remove or deactivate one of them")
        y0, x0 = (float(model.qpos0[model.jnt_qposadr[j]]) for j in (j1, j2))
        direct[j1], by[j1] = (j2, c[1], y0 + c[0] - c[1] * x0), name
    follow = {}
    for j in direct:  # compose: q_j = m q_lead + b, q_lead = m' q_lead' + b' -> (lead', m m', m b' + b)
        lead, m, b = direct[j]
        seen = [j]
        while lead in direct:
            if lead in seen:
                raise ModelError("joint equalities couple joints in a cycle ("
                                 f"{' -> '.join(jname(k) for k in [*seen, lead])}): no joint leads them")
            seen.append(lead)
            lead, m2, b2 = direct[lead]
            m, b = m * m2, m * b2 + b
        follow[j] = (lead, m, b)
    return follow, ignored


def _layout(model, build: _Builder, follow: dict) -> dict:
    """q slots, mimic couplings and per-frame offsets (−ref of hinges and slides) of the chain's joints:
    the frames of the description and the qpos / qvel bookkeeping."""
    mujoco = _mujoco()
    names, kinds, qpos_index, dof_index, slot = [], [], [], [], {}
    nq = 0
    for j in build.joints:
        if j in follow:
            continue
        kind = _kind(model, j)
        slot[j] = nq
        names.append(_name(model, mujoco.mjtObj.mjOBJ_JOINT, j) or f"joint{j}")
        kinds.append(kind.name)
        qa, da = int(model.jnt_qposadr[j]), int(model.jnt_dofadr[j])
        qpos_index.extend(range(qa, qa + kind.nq))
        dof_index.extend(range(da, da + kind.nv))
        nq += kind.nq
    if nq == 0:
        raise ModelError("every joint of the chain is held by an equality constraint: nothing moves")
    frames = []
    scalar = (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE)
    for f in build.frames:
        j = f["joint"]
        # MuJoCo's ref (the value of a hinge or slide in the model's pose) shifts the motion
        ref = float(model.qpos0[model.jnt_qposadr[j]]) if int(model.jnt_type[j]) in scalar else 0.0
        m, b = 1.0, 0.0
        if j in follow:  # a follower is a hinge or slide: one coordinate, its leader's
            lead, m, b = follow[j]
            q_index = slot[lead]
        else:
            q_index = slot[j] + f["qoff"]
        frames.append(FrameSpec(f["kind"], f["parent"], tuple(f["pre"]), tuple(f["post"]), q_index, m, b,
                                -ref))
    vslot = {j: dof_index.index(int(model.jnt_dofadr[j])) for j in slot}
    return {"frames": frames, "nq": nq, "joint_names": names, "joint_kinds": kinds,
            "qpos_index": qpos_index, "dof_index": dof_index,
            "followers": [(int(model.jnt_qposadr[j]), slot[lead], m, b)
                          for j, (lead, m, b) in follow.items()],
            "follower_dofs": [(int(model.jnt_dofadr[j]), vslot[lead], m)
                              for j, (lead, m, _) in follow.items()]}


def _limits(model, names: list[str], kinds: list[str]) -> list[list[float]]:
    """(nq, 2): hinge/slide ranges where limited, ±inf elsewhere (free positions, quaternions)."""
    mujoco = _mujoco()
    out = []
    for name, kind in zip(names, kinds):
        j = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)
        limited = bool(model.jnt_limited[j])
        lo, hi = (float(model.jnt_range[j, 0]), float(model.jnt_range[j, 1])) if limited else (None, None)
        out.extend(joint_kind(kind).limits(lo, hi))
    return out


def _parameters(model, build: _Builder, sites: list[int]) -> dict[str, Tensor]:
    """The learnable geometry (float64): body, joint and end-site rows of the compiled model."""

    def rows(values, width):
        return torch.tensor([list(v) for v in values], dtype=torch.float64).reshape(-1, width)

    return {"body_pos": rows((model.body_pos[b] for b in build.bodies), 3),
            "body_quat": rows((model.body_quat[b] for b in build.bodies), 4),
            "joint_pos": rows((model.jnt_pos[j] for j in build.anchor_joints), 3),
            "joint_axis": rows((model.jnt_axis[j] for j in build.axis_joints), 3),
            "site_pos": rows((model.site_pos[s] for s in sites), 3),
            "site_quat": rows((model.site_quat[s] for s in sites), 4)}


def _check_numbers(model, build: _Builder, sites: list[int], follow: dict) -> None:
    """Every number of the model the chain computes with is finite, and every body / site quaternion
    non-zero: a :class:`~diffkin.errors.ModelError` naming the element and attribute otherwise. MuJoCo
    compiles NaN and inf (it only prints a warning) and turns a quaternion whose entries overflow its
    normalisation (about 1e154) into (0, 0, 0, 0); the FK of either would be NaN or no rotation."""
    obj = _mujoco().mjtObj

    def bad(values) -> bool:
        return not all(math.isfinite(float(x)) for x in values)

    rows = [("body", obj.mjOBJ_BODY, b, "pos", model.body_pos[b]) for b in build.bodies]
    rows += [("body", obj.mjOBJ_BODY, b, "quat", model.body_quat[b]) for b in build.bodies]
    rows += [("joint", obj.mjOBJ_JOINT, j, "pos", model.jnt_pos[j]) for j in build.anchor_joints]
    rows += [("joint", obj.mjOBJ_JOINT, j, "axis", model.jnt_axis[j]) for j in build.axis_joints]
    rows += [("joint", obj.mjOBJ_JOINT, j, "ref", model.qpos0[model.jnt_qposadr[j]: model.jnt_qposadr[j] + 1])
             for j in build.axis_joints]
    rows += [("joint", obj.mjOBJ_JOINT, j, "range", model.jnt_range[j]) for j in build.axis_joints
             if model.jnt_limited[j]]
    rows += [("site", obj.mjOBJ_SITE, k, "pos", model.site_pos[k]) for k in sites]
    rows += [("site", obj.mjOBJ_SITE, k, "quat", model.site_quat[k]) for k in sites]
    rows += [("joint", obj.mjOBJ_JOINT, j, "equality (polycoef)", follow[j][1:]) for j in follow]
    for kind, o, i, attr, values in rows:
        what = f"MJCF {kind} {_name(model, o, i) or f'#{i}'!r}"
        if bad(values):
            raise ModelError(f"{what}: {attr} holds NaN or inf ({[float(x) for x in values]}); expected "
                             "finite numbers")
        if attr == "quat" and not any(float(x) for x in values):
            raise ModelError(f"{what}: quat is (0, 0, 0, 0) after MuJoCo compiled it (a zero quaternion, "
                             "or entries so large that its normalisation overflowed); give a non-zero "
                             "quaternion of moderate size")


def _describe(model, path: str | None, ends: list[str], root_link: str | None,
              text: str | None = None) -> tuple[TreeDescription, dict]:
    """The format-neutral description of the bodies between the root and the end links, and the MJCF
    facts the chain keeps (qpos / qvel maps, element rows of its parameters)."""
    mujoco = _mujoco()
    root = 0 if root_link is None else mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, root_link)
    if root < 0:
        raise ModelError(f"root_link {root_link!r} is not a body of the model")
    resolved = [_resolve_end(model, e) for e in ends]
    path_bodies: set[int] = set()
    for (b, _), name in zip(resolved, ends):
        chain_of, k = [], b
        while k != root:
            if k == 0:
                raise ModelError(f"end_link {name!r} does not hang below root_link {root_link!r}")
            chain_of.append(k)
            k = int(model.body_parentid[k])
        path_bodies.update(chain_of)
    build = _Builder(model, sorted(path_bodies), root)
    if not build.joints:
        raise ModelError(f"no joint between {root_link or 'the world'!r} and {ends}")
    follow, ignored = _couplings(model, build.joints)
    if ignored:
        warnings.warn(f"{path or 'MJCF'}: equality constraints not enforced by the kinematic chain: "
                      f"{', '.join(ignored)}", stacklevel=4)
    lay = _layout(model, build, follow)
    sites = [s for _, s in resolved if s is not None]
    _check_numbers(model, build, sites, follow)
    site_row = iter(range(len(sites)))
    end_factors = [list(build.pending[b]) + ([("site", next(site_row))] if s is not None else [])
                   for b, s in resolved]
    axes = torch.tensor([list(model.jnt_axis[j]) for j in build.axis_joints], dtype=torch.float64)
    description = TreeDescription(
        model.names.split(b"\0", 1)[0].decode() or Path(path or "mjcf").stem, lay["frames"],
        [build.last_frame[b] for b, _ in resolved], end_factors, lay["nq"],
        _limits(model, lay["joint_names"], lay["joint_kinds"]), lay["joint_names"], lay["joint_kinds"],
        parameters=_parameters(model, build, sites), buffers={"_axis_flip": axes.reshape(-1, 3)[:, 2] < 0})
    description.inertias, description.inertia_note = _inertias(model, build, root)
    if description.inertias and (text is not None or path is not None):
        stand_ins = _mass_from_stand_ins(text, path)
        inside = {b.name for b in description.inertias}
        description.inertia_note = ", ".join(b for b in stand_ins if b in inside)
    obj = mujoco.mjtObj
    facts = {**lay, "root_link": root_link or "world",
             "body_names": [_name(model, obj.mjOBJ_BODY, b) for b in build.bodies],
             "anchor_joints": list(build.anchor_joints), "axis_joints": list(build.axis_joints),
             "joint_rows": ([_name(model, obj.mjOBJ_JOINT, j) for j in build.anchor_joints],
                            [_name(model, obj.mjOBJ_JOINT, j) for j in build.axis_joints]),
             "site_names": [_name(model, obj.mjOBJ_SITE, s) for s in sites]}
    return description, facts


def _inertias(model, build: _Builder, root: int) -> tuple[list[BodyInertia] | None, str]:
    """MuJoCo's compiled mass and inertial frame (``body_mass``, ``body_ipos`` / ``body_iquat``) of every
    body in the root's subtree, attached to the frame of the nearest body on the chain's paths: the pose
    of the inertial frame relative to that frame, from ``mj_kinematics`` at ``qpos0`` (joints outside the
    chain sit there, as in :meth:`MJCFChain.to_qpos`). A frame is the pose of the body whose joints it
    ends (MuJoCo's xpos / xmat of that body)."""
    mujoco = _mujoco()
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)

    def pose(pos, mat):
        T = torch.eye(4, dtype=torch.float64)
        T[:3, :3] = torch.tensor(mat, dtype=torch.float64).reshape(3, 3)
        T[:3, 3] = torch.tensor(pos, dtype=torch.float64)
        return T

    frame_body = {-1: root, **{f: int(model.jnt_bodyid[spec["joint"]])
                               for f, spec in enumerate(build.frames)}}
    frame_inverse: dict[int, Tensor] = {}
    out = []
    for b in range(model.nbody):
        mass = float(model.body_mass[b])
        if mass <= 0.0:
            continue
        at = b
        while at not in build.last_frame and at != 0:  # the nearest body on the paths (or the root)
            at = int(model.body_parentid[at])
        if at not in build.last_frame:  # not in the root's subtree
            continue
        f = build.last_frame[at]
        if f not in frame_inverse:
            fb = frame_body[f]
            frame_inverse[f] = torch.linalg.inv(pose(data.xpos[fb], data.xmat[fb]))
        T = frame_inverse[f] @ pose(data.xipos[b], data.ximat[b])
        out.append(BodyInertia(_name(model, mujoco.mjtObj.mjOBJ_BODY, b) or f"body{b}", f, mass,
                               tuple(map(tuple, T.tolist()))))
    if not out:
        return None, "no body of the MJCF model below the root has a positive mass"
    return out, ""


def _mass_from_stand_ins(text: str | None, path: str | None) -> list[str]:
    """The bodies whose mass MuJoCo infers from a mesh geom (no ``<inertial>``, or ``<compiler
    inertiafromgeom="true">``): :func:`compile_mjcf` replaces their meshes by small spheres, so their
    compiled masses are not the file's."""
    mujoco = _mujoco()
    try:
        spec = mujoco.MjSpec.from_file(path) if path else mujoco.MjSpec.from_string(text)
    except (ValueError, mujoco.FatalError):  # compiled once already; nothing more to say
        return []
    rule = spec.compiler.inertiafromgeom
    if rule == mujoco.mjtInertiaFromGeom.mjINERTIAFROMGEOM_FALSE:
        return []
    always = rule == mujoco.mjtInertiaFromGeom.mjINERTIAFROMGEOM_TRUE
    return [b.name for b in spec.bodies[1:] if (always or not b.explicitinertial)
            and any(g.type == mujoco.mjtGeom.mjGEOM_MESH for g in b.geoms)]


class MJCFChain(TreeChain):
    """A MuJoCo model from its world (or ``root_link``) to one or several end bodies or sites.

    Parameters (learnable on request, like a URDF chain's: frozen unless ``learnable=True``):
    ``body_pos (L, 3)``, ``body_quat (L, 4)`` (normalised in the kernel) of the bodies on the paths
    (``body_names``; bodies with a free joint have none: their pose is q), ``joint_pos (A, 3)`` of the
    hinge, slide and ball joints, ``joint_axis (H, 3)`` of the hinge and slide joints, ``site_pos``,
    ``site_quat`` of end sites, plus the base/tool corrections of :class:`~diffkin.chain.KinematicChain`.
    The tree itself is the :class:`~diffkin.models.description.TreeDescription` the MJCF reader makes.

    Attributes: ``joint_names`` (the chain's independent joints, q's order), ``joint_kinds`` (``"revolute"``,
    ``"prismatic"``, ``"ball"``, ``"free"``, ``"continuous"``), ``qpos_index`` / ``dof_index`` (the model's
    qpos / qvel entries of q / v), ``end_links``, ``root_link``, ``qpos0`` (the model's reference qpos).
    """

    def __init__(self, model, text: str, path: str | None, end_links, root_link: str | None = None, *,
                 dtype: torch.dtype | None = None, device=None, learnable: bool = False):
        single, ends = check_end_links(end_links, "body or site")
        description, facts = _describe(model, path, ends, root_link, text)
        super().__init__(description, dtype=dtype, device=device, single_end=single, learnable=learnable)
        self.body_names = facts["body_names"]
        self._anchor_joints, self._axis_joints = facts["anchor_joints"], facts["axis_joints"]
        self._qpos_index, self._dof_index = facts["qpos_index"], facts["dof_index"]
        self._followers, self._follower_dofs = facts["followers"], facts["follower_dofs"]
        self.source_text, self.source_path = text, path
        geometry = ("body_pos", "body_quat", "joint_pos", "joint_axis", "site_pos", "site_quat")
        self._compiled0 = {k: getattr(self, k).detach().double().cpu().clone() for k in geometry}
        self._joint_rows = facts["joint_rows"]
        self.site_names = facts["site_names"]
        self.end_links, self.root_link = ends, facts["root_link"]
        # a buffer, so .to(dtype / device) moves it with the chain (not saved: the source file has it)
        self.register_buffer("qpos0", torch.tensor(model.qpos0, dtype=self.dtype, device=self.device),
                             persistent=False)
        self._nq_model, self._nv_model = int(model.nq), int(model.nv)

    # ---------------------------------------------------------------------------------- geometry
    def _factors(self, eye):
        B = _make_transform(_quaternion_to_matrix(_unit(self.body_quat)), self.body_pos).unbind(0)
        S = axis_alignment(self.joint_axis, self._axis_flip)
        zero = torch.zeros_like(self.joint_axis)
        I3 = eye[:3, :3].expand(self.joint_pos.shape[0], 3, 3)
        sites = _make_transform(_quaternion_to_matrix(_unit(self.site_quat)), self.site_pos).unbind(0)
        return {"B": B, "A": _make_transform(S, zero).unbind(0),
                "At": _make_transform(S.transpose(-1, -2), zero).unbind(0),
                "J": _make_transform(I3, self.joint_pos).unbind(0),
                "Jn": _make_transform(I3, -self.joint_pos).unbind(0), "site": sites}

    # ------------------------------------------------------------------------------------- qpos
    def from_qpos(self, qpos) -> Tensor:
        """The chain's q ``(..., nq)`` from the model's whole qpos ``(..., nq_model)``."""
        (qpos,) = tensors(("qpos", qpos, (self._nq_model,)), like=self)
        return qpos.index_select(-1, torch.tensor(self._qpos_index, device=qpos.device))

    def to_qpos(self, q) -> Tensor:
        """The model's qpos ``(..., nq_model)`` of the chain's ``q (..., nq)``: joints outside the chain
        take ``qpos0``; joints coupled by an equality follow their leader."""
        q = self.check_q(q)
        out = self.qpos0.expand(*q.shape[:-1], self._nq_model).clone()
        out[..., self._qpos_index] = q
        for adr, lead, m, b in self._followers:
            out[..., adr] = m * q[..., lead] + b
        return out

    def to_qvel(self, v) -> Tensor:
        """The model's qvel ``(..., nv_model)`` of the chain's velocity ``v (..., nv)``: joints outside the
        chain at rest, coupled joints at m times their leader's rate. ``J_model @ to_qvel`` as a matrix
        (:meth:`velocity_map`) turns MuJoCo's Jacobian into the chain's."""
        (v,) = tensors(("v", v, (self.nv,)), like=self)
        return v @ self.velocity_map().T

    def velocity_map(self) -> Tensor:
        """``(nv_model, nv)``: qvel = M v (identity on :meth:`dof_index`, the multiplier for followers)."""
        M = torch.zeros(self._nv_model, self.nv, dtype=self.dtype, device=self.device)
        M[self._dof_index, torch.arange(self.nv)] = 1.0
        for dof, lead, m in self._follower_dofs:
            M[dof, lead] = m
        return M

    def dof_index(self) -> list[int]:
        """The model's qvel entries of the chain's velocity columns (v and the Jacobian's columns)."""
        return list(self._dof_index)

    def qpos_index(self) -> list[int]:
        """The model's qpos entries of the chain's q."""
        return list(self._qpos_index)

    def to_mjcf(self, path=None) -> str:
        """The source MJCF with this chain's current geometry written in: the ``pos`` / ``quat`` of every body
        and end site whose parameters changed (relative to the enclosing ``<frame>`` s, orientation as
        ``quat``), and the ``pos`` / ``axis`` of changed joints; everything else in the text stays byte for
        byte. Also written to ``path`` if given; returns the text. ``from_mjcf`` of it gives the same FK.
        Elements must be named and in the main file (not in an ``<include>``); a base or tool transform
        has no place in an MJCF and is refused."""
        from .mjcf_write import write_mjcf

        return write_mjcf(self, path)

    def extra_repr(self) -> str:
        ends = self.end_links[0] if self._single_end else self.end_links
        return super().extra_repr() + f", end_link={ends!r}, joints={self.joint_names}"


def _unit(Q: Tensor) -> Tensor:
    """Q / |Q| with |Q| scaled first (:func:`~diffkin._numerics.stable_norm`: entries of 1e160 do not
    overflow to a zero quaternion)."""
    return Q / stable_norm(Q, keepdim=True)


def from_mjcf(source, end_link, *, root_link: str | None = None, dtype: torch.dtype | None = None,
              device=None, learnable: bool = False) -> MJCFChain:
    """A :class:`MJCFChain` from an MJCF path, XML text or bytes (UTF-8), from the world (or ``root_link``,
    a body) to ``end_link``: a body or site name, or a list of K of them for a tree whose FK is
    ``(..., K, 4, 4)`` and Jacobian ``(..., K, 6, nv)`` in that order. Several subtrees of the world (a robot
    and a movable object) may be in one chain. Needs the ``mujoco`` package (``pip install 'diffkin[mjcf]'``).

    ``dtype`` defaults to torch's default dtype, as for every loader (:func:`~diffkin.models.load`,
    :func:`~diffkin.models.from_urdf`); pass ``dtype=torch.float64`` for MuJoCo's own precision. In float32
    the joint limits are rounded inwards (:class:`~diffkin.chain.KinematicChain`), so a configuration the
    chain judges within its limits (IK's ``success``, ``within_limits``) is within the file's float64
    ranges too.

    Raises :class:`~diffkin.errors.ModelError` naming the source for files MuJoCo refuses, for text that is
    not UTF-8 and for a URDF (use :func:`~diffkin.models.from_urdf`), and naming the element for unknown end
    links or root links, NaN / inf numbers, zero quaternions and joint equalities a chain cannot hold (two
    on one follower, a cycle); :class:`~diffkin.errors.DeviceError` for a device this torch cannot compute
    on (``"cuda"`` without CUDA, ``"meta"``). The geometry is frozen unless ``learnable=True`` (see
    :class:`~diffkin.chain.KinematicChain`).
    """
    check_device(device)
    check_end_links(end_link, "body or site")  # before compiling: a wrong argument is said at once
    model, text, path = compile_mjcf(source)
    return MJCFChain(model, text, path, end_link, root_link, dtype=dtype or torch.get_default_dtype(),
                     device=device, learnable=learnable)

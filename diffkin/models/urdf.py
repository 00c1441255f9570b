"""URDF import: a serial chain of fixed transforms and joint axes (§2.8 without the DH restriction).

:func:`from_urdf` parses a URDF with pytorch-kinematics's bundled parser (``urdf_parser_py``; the numbers are
read as Python floats, so a float64 chain is exact) and folds it into a :class:`URDFChain`: for joint i a
fixed origin O_i (from the previous link frame, fixed joints folded in) and a unit axis k_i in the joint
frame; link frame i = link frame (i−1) · O_i · Rot(k_i, q_i) (revolute, Rodrigues (2.25)) or
· Trans(k_i q_i) (prismatic). Fixed joints after the last moving joint become the tool.

The kernel rotates each joint frame once, at construction, so that k_i is its z axis (O_i S_i with
S_i e_z = k_i, and S_i^T folded into the next origin): every joint is then an Rz or a Tz, the same few
column updates as the DH kernel, and the fixed rotations, mostly signed permutations in real URDFs, are
applied with their zero terms skipped.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from .._fk_kernels import Columns
from ..chain import KinematicChain
from ..errors import ModelError

__all__ = ["URDFChain", "from_urdf"]

_Plan = tuple[tuple[tuple[float, ...], ...], tuple[float, ...]]  # (R 3x3, t 3) as Python floats


def _snap(M: np.ndarray) -> np.ndarray:
    M = M.copy()
    M[np.abs(M) < 1e-15] = 0.0
    return M


def _align_z(k: np.ndarray) -> np.ndarray:
    """Rotation S (3x3) with S e_z = k (Rodrigues about e_z × k); exact for axis-aligned k."""
    if k[2] > 1.0 - 1e-15:
        return np.eye(3)
    if k[2] < -1.0 + 1e-15:
        return np.diag([1.0, -1.0, -1.0])
    u = np.cross([0.0, 0.0, 1.0], k)
    s = np.linalg.norm(u)
    u = u / s
    c = k[2]
    K = np.array([[0, -u[2], u[1]], [u[2], 0, -u[0]], [-u[1], u[0], 0]])
    return _snap(np.eye(3) + s * K + (1.0 - c) * (K @ K))


def _homog(R: np.ndarray, t=None) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    if t is not None:
        T[:3, 3] = t
    return T


def _plan(T: np.ndarray) -> _Plan:
    return tuple(tuple(float(v) for v in row) for row in T[:3, :3]), tuple(float(v) for v in T[:3, 3])


def _combo(terms: list[tuple[float, Tensor]]) -> Tensor:
    """sum coef * tensor over the nonzero terms (±1 without a multiply)."""
    (c0, v0), rest = terms[0], terms[1:]
    acc = v0 if c0 == 1.0 else -v0 if c0 == -1.0 else v0 * c0
    for c, v in rest:
        acc = torch.add(acc, v, alpha=c)
    return acc


def _apply_fixed(plan: _Plan, frame: Columns) -> Columns:
    """Columns of F · T for a fixed T given as a plan, skipping zero entries."""
    R, t = plan
    cols = frame[:3]
    new = [_combo([(R[k][j], cols[k]) for k in range(3) if R[k][j] != 0.0]) for j in range(3)]
    terms = [(t[k], cols[k]) for k in range(3) if t[k] != 0.0]
    p = _combo([(1.0, frame[3]), *terms]) if terms else frame[3]
    return new[0], new[1], new[2], p


class URDFChain(KinematicChain):
    """General serial chain: fixed joint origins ``O_i (n, 4, 4)``, unit axes ``k_i (n, 3)``, tool.

    Link frame i = link frame (i−1) · O_i · Rot(k_i, q_i) for 'R' joints, · Trans(q_i k_i) for 'P' joints;
    link frame 0 is the root (``base``, default identity). ``joint_names`` and ``link_names`` (the child
    link of each joint: frame i of ``forward_kinematics(q, all_frames=True)``) label them. The geometry is
    fixed (buffers, not parameters).
    Same interface as :class:`~diffkin.chain.DHChain`: ``forward_kinematics``, ``joint_axes_origins``
    (joint i moves about k_i through the origin of its joint frame), limits, Jacobians.
    """

    _axis_offset = 1

    def __init__(self, joint_origins, joint_axes, joint_types: str, tool=None, q_limits=None,
                 name: str | None = None, joint_names=None, base=None, *, link_names=None, dtype=None,
                 device=None):
        O = np.asarray(torch.as_tensor(joint_origins, dtype=torch.float64).cpu(), dtype=np.float64)
        K = np.asarray(torch.as_tensor(joint_axes, dtype=torch.float64).cpu(), dtype=np.float64)
        n = O.shape[0]
        if O.shape != (n, 4, 4) or K.shape != (n, 3) or n == 0:
            raise ModelError(
                f"joint_origins must be (n, 4, 4) and joint_axes (n, 3), got {O.shape}, {K.shape}"
            )
        norms = np.linalg.norm(K, axis=1)
        if not np.all(norms > 1e-9):
            raise ModelError(f"joint axes must be non-zero, got norms {norms.tolist()}")
        K = K / norms[:, None]
        super().__init__(n, joint_types, q_limits=q_limits, name=name, dtype=dtype, device=device)
        self._set_base_tool(base, tool)
        default_names = [f"joint{i + 1}" for i in range(n)]
        self.joint_names = list(joint_names) if joint_names is not None else default_names
        self.link_names = list(link_names) if link_names is not None else [f"link{i + 1}" for i in range(n)]
        dtype, device = self.dtype, self.device
        self.register_buffer("joint_origins", torch.tensor(O, dtype=dtype, device=device))
        self.register_buffer("joint_axes", torch.tensor(K, dtype=dtype, device=device))
        S = [_homog(_align_z(k)) for k in K]
        folded = [O[0] @ S[0]] + [S[i - 1].T @ O[i] @ S[i] for i in range(1, n)]
        tool64 = np.eye(4) if self.tool is None else self.tool.detach().cpu().double().numpy()
        ee = S[-1].T @ tool64
        self.register_buffer("_folded", torch.tensor(np.stack(folded), dtype=dtype, device=device))
        self.register_buffer("_fixups", torch.tensor(np.stack([s.T for s in S]), dtype=dtype, device=device))
        self.register_buffer("_ee", torch.tensor(ee, dtype=dtype, device=device))
        self._has_fixup = [not np.array_equal(s, np.eye(4)) for s in S]
        self._ee_is_identity = bool(np.array_equal(ee, np.eye(4)))
        self._plans = [_plan(T) for T in folded]

    # -------------------------------------------------------------------------------------- kernels
    def _column_frames(self, qs: Sequence[Tensor], constants: bool = True) -> Iterator[Columns]:
        frame = self._base_columns(qs[0])
        yield frame
        for i in range(self.n_joints):
            x, y, z, p = _apply_fixed(self._plans[i], frame)
            if self.joint_types[i] == "R":  # · Rz(q)
                c, s = torch.cos(qs[i]), torch.sin(qs[i])
                x, y = torch.addcmul(c * x, s, y), torch.addcmul(c * y, s, x, value=-1.0)
            else:  # · Tz(q)
                p = torch.addcmul(p, qs[i], z)
            frame = (x, y, z, p)
            yield frame

    def _link_matrices(self, q: Tensor) -> Tensor:
        rev = self.revolute_mask > 0
        c = torch.where(rev, torch.cos(q), 1.0)
        s = torch.where(rev, torch.sin(q), 0.0)
        tz = torch.where(rev, 0.0, q)
        zero, one = torch.zeros_like(q), torch.ones_like(q)
        rows = (c, -s, zero, zero, s, c, zero, zero, zero, zero, one, tz, zero, zero, zero, one)
        J = torch.stack(rows, dim=-1)
        return self._folded @ J.unflatten(-1, (4, 4))

    def _frame_fixup(self, i: int) -> Tensor | None:
        return self._fixups[i - 1] if self._has_fixup[i - 1] else None

    def _ee_transform(self) -> Tensor | None:
        return None if self._ee_is_identity else self._ee

    def copy(self) -> URDFChain:
        """An independent deep copy (not compiled: a compiled path is bound to its own chain)."""
        fast, self._compiled_fk = self._compiled_fk, None
        try:
            return copy.deepcopy(self)
        finally:
            self._compiled_fk = fast

    def extra_repr(self) -> str:
        return super().extra_repr() + f", joints={self.joint_names}"


# --------------------------------------------------------------------------------------------- parsing
def _read_source(source) -> str:
    if isinstance(source, bytes):
        return source.decode()
    text = str(source)
    if "<robot" in text:
        return text
    path = Path(text)
    if not path.is_file():
        raise ModelError(f"URDF {text!r} is neither an existing file nor URDF XML text")
    return path.read_text()


def _origin_matrix(origin) -> np.ndarray:
    from .io import rpy_to_matrix

    xyz = list(getattr(origin, "xyz", None) or [0.0, 0.0, 0.0])
    rpy = list(getattr(origin, "rpy", None) or [0.0, 0.0, 0.0])
    return _homog(np.array(rpy_to_matrix(rpy)), xyz)


def _serial_joints(robot, end_link: str, root_link: str | None) -> list:
    links = {link.name for link in robot.links}
    if end_link not in links:
        raise ModelError(f"end link {end_link!r} not in the URDF; links: {sorted(links)}")
    if root_link is not None and root_link not in links:
        raise ModelError(f"root link {root_link!r} not in the URDF; links: {sorted(links)}")
    parent_joint = {j.child: j for j in robot.joints}
    chain, link = [], end_link
    while link != root_link and link in parent_joint:
        j = parent_joint[link]
        chain.append(j)
        link = j.parent
    if root_link is not None and link != root_link:
        raise ModelError(f"{root_link!r} is not an ancestor of {end_link!r}")
    return chain[::-1]


def from_urdf(source, end_link: str, dtype: torch.dtype | None = None, device=None, *,
              root_link: str | None = None) -> URDFChain:
    """A :class:`URDFChain` from the URDF file path or XML text ``source``, from ``root_link`` (default: the
    tree's root) to ``end_link``. Revolute, continuous (limits ±π) and prismatic joints move; fixed joints
    are folded into the neighbouring transforms. Parsed with pytorch-kinematics's ``urdf_parser_py``.
    """
    try:
        from pytorch_kinematics.urdf_parser_py.urdf import URDF
    except ImportError as e:  # pragma: no cover - pk is a dev dependency
        raise ImportError("from_urdf needs pytorch-kinematics (pip install pytorch-kinematics)") from e
    robot = URDF.from_xml_string(_read_source(source))
    origins, axes, types, limits, names, links = [], [], "", [], [], []
    acc = np.eye(4)
    for j in _serial_joints(robot, end_link, root_link):
        T = _origin_matrix(j.origin)
        if j.type == "fixed":
            acc = acc @ T
            continue
        if j.type not in ("revolute", "continuous", "prismatic"):
            raise ModelError(f"joint {j.name!r}: type {j.type!r} is not supported (revolute, continuous, "
                             f"prismatic, fixed)")
        if getattr(j, "mimic", None) is not None:
            raise ModelError(f"joint {j.name!r}: mimic joints are not supported")
        origins.append(acc @ T)
        acc = np.eye(4)
        axes.append(list(j.axis) if j.axis is not None else [1.0, 0.0, 0.0])
        types += "P" if j.type == "prismatic" else "R"
        lim = getattr(j, "limit", None)
        if j.type == "continuous" or lim is None or lim.lower is None or lim.upper is None:
            limits.append([-math.pi, math.pi])
        else:
            limits.append([float(lim.lower), float(lim.upper)])
        names.append(j.name)
        links.append(j.child)
    if not origins:
        raise ModelError(f"no moving joint between the root and {end_link!r}")
    tool = None if np.array_equal(acc, np.eye(4)) else acc
    dtype = dtype or torch.get_default_dtype()
    return URDFChain(np.stack(origins), np.array(axes, dtype=np.float64), types, tool=tool,
                     q_limits=limits, name=robot.name, joint_names=names, link_names=links, dtype=dtype,
                     device=device)

"""Error models on the chain's own parameters: Hayati's β for DH chains, per-joint origins for URDF chains.

The ``"dh"`` model (:class:`~diffkin.calibration.model.CalibrationModel`) estimates the DH table. The
models here estimate a subset of a :class:`~diffkin.chain.KinematicChain`'s
own ``nn.Parameter`` s, so the calibrated robot is the same kind of object as the nominal one:

- ``"hayati"`` (a :class:`~diffkin.chain.DHChain`): a, α, d, ϑ per joint, except that for every pair of
  consecutive joint axes that are (nearly) parallel — |sin α_i| < :data:`PARALLEL_SIN`, i < n — Hayati's
  β_i (A_i = (2.52) · Ry(β_i), a tilt of axis i + 1 in the plane of the two axes) is estimated in place of
  d_i, which stays at its nominal value (Hayati & Mirmirani 1985). The DH table alone cannot represent such a
  tilt: d_i jumps to infinity. The result is a DHChain with a ``beta`` column (``to_yaml`` carries it).
- ``"general"`` (a :class:`~diffkin.models.urdf.URDFChain`): a six-parameter correction of the origin of
  every moving joint and of the fixed joints after the last one (the tail to the end link): origin · Δ(δ),
  δ = (translation, rotation vector) in the origin's frame (``URDFChain.origin_delta``), free of the gimbal
  lock of URDF rpy angles (pitch ±π/2 is common: UR arms); folded into xyz/rpy in the result. Fixed joints
  between moving ones are exactly absorbed by the next moving joint's origin and are not candidates; encoder
  offsets are rotations of the origin about the joint axis, so ``joint_offsets`` adds nothing here. Six
  numbers per joint are more than the 4 (revolute) or 2 (prismatic) a joint's line needs: the
  identifiability analysis (:mod:`.identifiability`) drops the redundant ones. The result is a URDFChain
  that ``to_urdf`` writes.

All three compute the calibration matrix Φ (2.86) by the one
:class:`~diffkin.calibration.model.ForwardModeMatrix`: the base-frame twist of the end effector per unit
change of each candidate, by forward-mode differentiation of the one FK kernel (what
:meth:`~diffkin.chain.KinematicChain.parameter_jacobian` does), vectorised over K robots with ``torch.func``.
The interface is that of ``CalibrationModel`` (ζ ``(K, P)``: the flattened parameters; ``candidate``
``(P,)``), so the solvers and the identifiability analysis serve all error models.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import torch
from torch import Tensor, nn

from .._unchecked import UncheckedFK as _FK  # FK without checks, for torch.func over robots
from ..chain import DHChain, KinematicChain
from ..errors import ModelError
from .model import (
    DH_KINDS,
    POSE_AXES,
    CalibrationModel,
    ForwardModeMatrix,
    ParameterLayout,
    learnable_like,
    pose_residual,
)

__all__ = ["build_model", "ChainErrorModel", "ERROR_MODELS", "PARALLEL_SIN", "parallel_pairs",
           "resolve_error_model"]

ERROR_MODELS = ("auto", "dh", "hayati", "general")
#: consecutive axes with |sin α_i| below this are treated as parallel (β_i replaces d_i): about 2.9°
PARALLEL_SIN = 0.05
_RPY = ("roll", "pitch", "yaw")


def parallel_pairs(chain: DHChain) -> list[int]:
    """0-based rows i < n - 1 of a standard-DH chain whose revolute joint i+1's axis z_i and the next axis
    z_{i+1} (joints i+1, i+2 in the book's numbering) are nearly parallel: |sin α| < :data:`PARALLEL_SIN`
    (a prismatic joint's d is its variable and stays)."""
    if chain.convention != "standard":
        return []
    s = torch.sin(chain.alpha.detach()).abs().tolist()
    return [i for i in range(chain.n_joints - 1) if s[i] < PARALLEL_SIN and chain.joint_types[i] == "R"]


def resolve_error_model(chain, error_model: str) -> str:
    """``"auto"`` -> ``"general"`` for URDF chains, ``"hayati"`` for DH chains with near-parallel consecutive
    axes, ``"dh"`` otherwise; explicit choices are checked against the chain's kind."""
    from ..models.mjcf import MJCFChain
    from ..models.urdf import URDFChain

    if error_model not in ERROR_MODELS:
        raise ModelError(f"unknown error_model {error_model!r}; valid: {', '.join(ERROR_MODELS)}")
    first = chain[0] if isinstance(chain, (list, tuple)) else chain
    if isinstance(first, URDFChain | MJCFChain):
        if error_model not in ("auto", "general"):
            kind = "a URDF" if isinstance(first, URDFChain) else "an MJCF"
            raise ModelError(f"error_model {error_model!r} needs a DHChain; {kind} chain uses 'general'")
        return "general"
    if not isinstance(first, DHChain):
        raise ModelError("calibration needs a DHChain, a URDFChain or an MJCFChain, got "
                         f"{type(first).__name__}")
    if error_model == "general":
        raise ModelError("error_model 'general' needs a URDF chain (diffkin.models.from_urdf); for a DHChain "
                         "use 'hayati' (DH with Hayati's beta for parallel axes) or 'dh'")
    if error_model == "hayati" and first.convention != "standard":
        raise ModelError("error_model 'hayati' is defined for the standard DH convention")
    if error_model == "auto":
        return "hayati" if parallel_pairs(first) or first.beta is not None else "dh"
    return error_model


_MJCF_GEOMETRY = ("body_pos", "body_quat", "joint_pos", "joint_axis", "site_pos", "site_quat")


def _origin_corrected(chain) -> bool:
    """A URDF chain: its "general" model estimates 6-DOF origin corrections (an MJCF chain: its own
    geometry parameters)."""
    return hasattr(chain, "fold_origins")


def _mjcf_rows(chain, key: str) -> list[str]:
    """The names of the rows of an MJCF chain's geometry parameter ``key``."""
    if key.startswith("body"):
        return list(chain.body_names)
    if key.startswith("site"):
        return list(chain.site_names)
    anchors, axes = chain._joint_rows
    return list(anchors if key == "joint_pos" else axes)


def _names_units(chain: KinematicChain, named) -> tuple[list[str], list[bool]]:
    """Readable names and is-length flags of the flattened parameters."""
    names, length = [], []
    for key, p in named:
        key = key.removeprefix("chain.")
        n = p.numel()
        if key in ("base_delta", "tool_delta"):
            names += [f"{key[:4]}_{s}" for s in POSE_AXES]
            length += [True, True, True, False, False, False]
        elif key in DH_KINDS + ("beta",):
            names += [f"{key}{i + 1}" for i in range(n)]
            length += [key in ("a", "d")] * n
        elif key == "origin_xyz":
            names += [f"{j}.{c}" for j in chain.joint_origin_names for c in "xyz"]
            length += [True] * n
        elif key == "origin_rpy":
            names += [f"{j}.{c}" for j in chain.joint_origin_names for c in _RPY]
            length += [False] * n
        elif key == "origin_delta":
            comps = ("dx", "dy", "dz", "rx", "ry", "rz")
            names += [f"{j}.{c}" for j in chain.joint_origin_names for c in comps]
            length += [True, True, True, False, False, False] * (n // 6)
        elif key in _MJCF_GEOMETRY:
            rows = _mjcf_rows(chain, key)
            comps = "wxyz" if key.endswith("quat") else "xyz"
            names += [f"{r}.{key.split('_')[1]}_{c}" for r in rows for c in comps]
            length += [key.endswith("pos")] * n
        elif key == "axis":
            names += [f"{j}.axis_{c}" for j in chain.frame_joint_names for c in "xyz"]
            length += [False] * n
        else:
            names += [f"{key}.{i}" for i in range(n)]
            length += [False] * n
    return names, length


class ChainErrorModel(ParameterLayout, ForwardModeMatrix):
    """The ``"hayati"`` or ``"general"`` error model of one chain structure for K robots (see module doc).

    ``nominal``: ζ_n ``(P,)`` or ``(K, P)``; ``candidate`` ``(P,)`` bool; ``names``; ``chains``: the nominal
    chains; ``notes``: what the model decided (which β replace which d, what joint offsets map to).
    """

    def __init__(
        self,
        chains: KinematicChain | Sequence[KinematicChain],
        kind: str,
        parameters: str | Iterable[str] = "all",
        base: bool = False,
        tool: bool = False,
        joint_offsets: bool = True,
    ):
        single = isinstance(chains, KinematicChain)
        chains = (chains,) if single else tuple(chains)
        if not chains:
            raise ModelError("calibration needs a chain (or a non-empty sequence of chains)")
        self.kind = kind
        self.chains = chains
        self.notes: list[str] = []
        ref = chains[0]
        work = []
        for c in chains:
            w = c.copy()
            if type(w) is not type(ref) or w.n_joints != ref.n_joints or w.joint_types != ref.joint_types:
                raise ModelError(f"all nominal chains of a batch must share their structure; '{c.name}' "
                                 f"differs from '{ref.name}'")
            if kind == "hayati" and w.beta is None:
                w.beta = nn.Parameter(torch.zeros_like(w.a))
            if kind == "general" and _origin_corrected(w):
                w.fold_origins()
                w.origin_delta = torch.zeros_like(w.origin_xyz.detach()).repeat(1, 2)
            for p in w.parameters():
                p.requires_grad_(False)
            work.append(w)
        self.work = work
        self.module = _FK(work[0])
        self._named = self._entries(self.module)
        self._sizes = [p.numel() for _, p in self._named]
        flat = [torch.cat([p.detach().reshape(-1) for _, p in self._entries(_FK(w))]) for w in work]
        self.nominal = flat[0] if single else torch.stack(flat)
        names, length = _names_units(ref, self._named)
        self.names = tuple(names)
        self._length = torch.tensor(length, device="cpu")  # host masks: moved where used
        self.n = ref.n_joints
        self.candidate = self._select(ref, parameters, base, tool, joint_offsets)

    def _entries(self, module: nn.Module) -> list[tuple[str, Tensor]]:
        """The estimated tensors: the chain's parameters, plus the origin corrections of a URDF chain."""
        out = list(module.named_parameters())
        if self.kind == "general" and _origin_corrected(module.chain):
            out.append(("chain.origin_delta", module.chain.origin_delta))
        return out

    # ------------------------------------------------------------------------------- selection
    def _slice(self, key: str) -> slice:
        start = 0
        for (k, _), n in zip(self._named, self._sizes):
            if k == f"chain.{key}":
                return slice(start, start + n)
            start += n
        raise KeyError(key)

    def _select(self, ref, parameters, base: bool, tool: bool, joint_offsets: bool) -> Tensor:
        P = len(self.names)
        mask = torch.zeros(P, dtype=torch.bool, device="cpu")
        index = {nm: j for j, nm in enumerate(self.names)}
        if self.kind == "hayati":
            n = self.n
            kinds = {k: self._slice(k) for k in DH_KINDS + ("beta",)}
            pairs = parallel_pairs(ref)
            if isinstance(parameters, str):
                parameters = ("a", "alpha", "d", "theta", "beta") if parameters == "all" else (parameters,)
            for item in parameters:
                if item in kinds:
                    mask[kinds[item]] = True
                elif item in index:
                    mask[index[item]] = True
                else:
                    raise ModelError(f"unknown calibration parameter {item!r}; use 'all', a kind "
                                     f"{DH_KINDS + ('beta',)} or a name such as 'a2', 'beta2', 'base_z'")
            beta = torch.zeros(n, dtype=torch.bool, device="cpu")
            beta[pairs] = True
            mask[kinds["beta"]] &= beta  # β only where the axes are parallel ...
            d = mask[kinds["d"]].clone()
            d[pairs] = False  # ... and d_i stays nominal there
            mask[kinds["d"]] = d
            for i, jt in enumerate(ref.joint_types):  # encoder zero: ϑ (revolute) / d (prismatic)
                sl = kinds["theta"] if jt == "R" else kinds["d"]
                mask[sl.start + i] = bool(joint_offsets) and not (jt == "P" and i in pairs)
            if pairs:
                self.notes.append("Hayati: beta replaces d for the near-parallel axes of rows "
                                  + ", ".join(f"{i + 1}-{i + 2}" for i in pairs) + " (d kept nominal)")
        else:  # general: the origins of the moving joints and of the tail to the end link
            if parameters != "all":
                items = (parameters,) if isinstance(parameters, str) else tuple(parameters)
                for item in items:
                    if item not in index:
                        example = self.names[self._slice("origin_delta").start]
                        raise ModelError(f"unknown calibration parameter {item!r}; use 'all' or names "
                                         f"such as '{example}', 'base_z'")
                    mask[index[item]] = True
            elif not _origin_corrected(ref):  # MJCF: the body, joint and site geometry on the paths
                for key in _MJCF_GEOMETRY:
                    mask[self._slice(key)] = True
            else:
                moving = set(ref.frame_joint_names)
                last = max(i for i, nm in enumerate(ref.joint_origin_names) if nm in moving)
                rows = [i for i, nm in enumerate(ref.joint_origin_names) if nm in moving or i > last]
                sl = self._slice("origin_delta")
                for r in rows:
                    mask[sl.start + 6 * r : sl.start + 6 * r + 6] = True
            if not _origin_corrected(ref):
                self.notes.append("general (MJCF): the bodies' pos/quat, the joints' pos/axis and the end "
                                  "sites' pos/quat; the redundant directions (quaternion and axis norms, "
                                  "shifts along an axis) are fixed by the identifiability analysis")
                return self._base_tool(mask, base, tool)
            self.notes.append("general: a 6-DOF correction of each joint origin (local translation dx, dy, "
                              "dz and rotation vector rx, ry, rz: no gimbal lock of rpy); encoder offsets "
                              "are rotations of the origins about the joint axes (no separate parameter); "
                              "the result has them folded into the URDF origins")
        return self._base_tool(mask, base, tool)

    def _base_tool(self, mask: Tensor, base: bool, tool: bool) -> Tensor:
        for key, flag in (("base_delta", base), ("tool_delta", tool)):
            if flag:
                mask[self._slice(key)] = True
        return mask

    # ------------------------------------------------------------------------------ kinematics
    def _fk_one(self, theta: Tensor, q: Tensor) -> Tensor:
        parts = torch.split(theta, self._sizes)
        params = {k: t.view_as(p) for (k, p), t in zip(self._named, parts)}
        return torch.func.functional_call(self.module, params, (q,))

    def forward_kinematics(self, zeta: Tensor, q: Tensor) -> Tensor:
        """End-effector poses ``(K, N, 4, 4)`` of ``zeta (K, P)`` (or ``(P,)``) at ``q (K, N, n)``."""
        if zeta.ndim == 1:
            return self._fk_one(zeta, q)
        return torch.func.vmap(self._fk_one)(zeta, q)

    def residual(self, zeta: Tensor, q: Tensor, measured: Tensor, orientation_weight: float) -> Tensor:
        return pose_residual(self.forward_kinematics(zeta, q), measured, orientation_weight)

    # -------------------------------------------------------------------------------- chains
    def to_chains(self, zeta: Tensor, first: int = 0) -> list[KinematicChain]:
        """One new chain per row of ``zeta (K, P)`` (row k from nominal chain ``first + k``), same kind."""
        out = []
        for k in range(zeta.shape[0]):
            ref = self.work[min(first + k, len(self.work) - 1)]
            c = ref.copy()
            parts = torch.split(zeta[k].detach(), self._sizes)
            with torch.no_grad():
                for (key, _), t in zip(self._named, parts):
                    name = key.removeprefix("chain.")
                    p = c.get_buffer(name) if name == "origin_delta" else c.get_parameter(name)
                    p.copy_(t.view_as(p))
            if self.kind == "general" and _origin_corrected(c):
                c.fold_origins()
            src = self.chains[min(first + k, len(self.chains) - 1)]
            learnable_like(c, src)
            c.metadata = dict(getattr(src, "metadata", {}))
            out.append(c)
        return out

    def to_chain(self, zeta: Tensor, index: int = 0) -> KinematicChain:
        return self.to_chains(zeta[None], first=index)[0]


def build_model(chain, error_model: str = "auto", parameters="all", base: bool = False, tool: bool = False,
                joint_offsets: bool = True):
    """``(model, kind)``: the calibration model of ``chain`` (one or a sequence) for ``error_model``."""
    kind = resolve_error_model(chain, error_model)
    if kind == "dh":
        return CalibrationModel.from_chains(chain, parameters, base, tool, joint_offsets), kind
    return ChainErrorModel(chain, kind, parameters, base, tool, joint_offsets), kind

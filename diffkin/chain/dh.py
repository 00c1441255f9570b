"""Serial chains from a Denavit–Hartenberg table (§2.8.2): :class:`DHChain`."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from ..errors import ConventionError, DTypeError, ModelError, ShapeError
from ..kernels.joints import dh_joints
from ..kernels.tree import Topology
from ..validation import SUPPORTED_DTYPES, check_dtype, shape_str, tensors
from .kinematic import KinematicChain, _check_learnable

__all__ = ["DHChain"]

_CONVENTIONS = ("standard", "modified")


def _dh_columns(columns: dict, dtype: torch.dtype | None, device) -> dict[str, Tensor | None]:
    """The DH columns by the rule of :mod:`diffkin.validation` (one float dtype; numbers and numpy arrays
    converted; finite), each ``(n,)`` or a 0-d value for every joint. An explicit ``dtype`` converts float
    tensors of the other float dtype (the caller asked for it)."""
    if dtype is not None:
        columns = {k: check_dtype(v, k).detach().to(dtype) if isinstance(v, Tensor) else v
                   for k, v in columns.items()}
        like = torch.empty(0, dtype=dtype, device=device)
        if device is None:
            like = next((v for v in columns.values() if isinstance(v, Tensor)), like)
            like = torch.empty(0, dtype=dtype, device=like.device)
    else:
        like = None
    out = tensors(*((k, v, None) for k, v in columns.items()), like=like)
    if device is not None:
        out = tuple(None if t is None else t.to(device) for t in out)
    a = out[0]
    if a.ndim != 1:
        raise ShapeError(f"expected the DH column a of shape (n,), got {shape_str(a.shape)}")
    n = a.shape[0]
    if n == 0:
        raise ModelError("a DH chain needs at least one joint")
    cols = {}
    for name, t in zip(columns, out):
        if t is not None:
            t = t.detach().expand(n) if t.ndim == 0 else t.detach()
            if t.shape != (n,):
                raise ShapeError(f"expected {name} of shape ({n},) like a (one value per joint), got "
                                 f"{shape_str(t.shape)}")
            t = t.clone()
        cols[name] = t
    return cols


class DHChain(KinematicChain):
    """Serial chain from a Denavit–Hartenberg table (§2.8.2).

    ``a``, ``alpha``, ``d``, ``theta`` (each ``(n,)``) are ``nn.Parameter`` s, frozen unless
    ``learnable=True`` (or ``chain.requires_grad_()``): then FK is differentiable with respect to the DH
    table (gradient-based identification, a learnt tool). For a revolute joint ``theta`` is the
    joint offset (ϑ_i = theta_i + q_i); for a prismatic joint ``theta`` is its constant angle and
    d_i = d_i + q_i (2.52).

    convention="standard" (the book's): A_i = Rz(ϑ_i) Tz(d_i) Tx(a_i) Rx(α_i)  (2.52).
    convention="modified" (Craig): row i holds (a_{i-1}, α_{i-1}, d_i, ϑ_i) and
    A_i = Rx(α_{i-1}) Tx(a_{i-1}) Rz(ϑ_i) Tz(d_i).
    ``beta`` (standard convention only): Hayati's parameters, A_i = (2.52) · Ry(β_i); for near-parallel
    consecutive axes, where d is ill-defined, a small tilt of the next axis in their common plane is a small
    β.

    ``base`` and ``tool`` are ``(4, 4)`` transforms T^b_0 and T^n_e (2.51), learnable through ``base_delta``
    and ``tool_delta``; ``q_limits`` is ``(n, 2)``. The DH columns follow the rule of
    :mod:`diffkin.validation`: float32/float64 tensors of one dtype (mixed dtypes, integer or half tensors
    raise :class:`~diffkin.errors.DTypeError`; NaN/inf :class:`~diffkin.errors.NonFiniteError`; columns of
    another length :class:`~diffkin.errors.ShapeError`), numbers and numpy arrays converted. The chain's
    dtype is ``dtype`` if given (float tensors are then converted to it), else the columns'; Python numbers
    are converted straight to it, so float64 tables are exact. ``base``/``tool`` follow the chain's dtype.
    """

    def __init__(
        self,
        a,
        alpha,
        d,
        theta,
        joint_types: str | None = None,
        convention: str = "standard",
        base=None,
        tool=None,
        q_limits=None,
        name: str | None = None,
        *,
        beta=None,
        dtype: torch.dtype | None = None,
        device=None,
        learnable: bool = False,
    ):
        _check_learnable(learnable)
        if convention not in _CONVENTIONS:
            raise ConventionError(f"convention must be one of {_CONVENTIONS}, got {convention!r}")
        if beta is not None and convention != "standard":
            raise ConventionError("Hayati's beta is defined here for the standard DH convention only")
        if dtype is not None and dtype not in SUPPORTED_DTYPES:
            raise DTypeError(f"a chain's dtype must be torch.float32 or torch.float64, got {dtype}")
        cols = _dh_columns({"a": a, "alpha": alpha, "d": d, "theta": theta, "beta": beta}, dtype, device)
        n = cols["a"].shape[0]
        dtype, device = cols["a"].dtype, cols["a"].device
        joint_types = "R" * n if joint_types is None else joint_types
        joint_types = joint_types.upper() if isinstance(joint_types, str) else joint_types
        if not isinstance(joint_types, str) or len(joint_types) != n or set(joint_types) - {"R", "P"}:
            raise ModelError(
                f"joint_types must be a string of {n} letters 'R' (revolute) or 'P' (prismatic), "
                f"got {joint_types!r}"
            )
        topo = Topology.serial(joint_types)
        super().__init__(topo, q_limits=q_limits, name=name, dtype=dtype, device=device, learnable=learnable)
        self.convention = convention
        self.a = nn.Parameter(cols["a"], requires_grad=learnable)
        self.alpha = nn.Parameter(cols["alpha"], requires_grad=learnable)
        self.d = nn.Parameter(cols["d"], requires_grad=learnable)
        self.theta = nn.Parameter(cols["theta"], requires_grad=learnable)
        self.beta = None if beta is None else nn.Parameter(cols["beta"], requires_grad=learnable)
        # the constructor decides the chain's dtype: float base/tool tensors are converted to it
        base, tool = (check_dtype(T, k).detach().to(dtype) if isinstance(T, Tensor) else T
                      for k, T in (("base", base), ("tool", tool)))
        self._set_base_tool(base, tool)

    def _geometry(self):
        pre, offset, post = dh_joints(self.a, self.alpha, self.d, self.theta, self.revolute_mask,
                                      self.convention == "modified", self.beta)
        return pre, offset, post, [None]

    # ------------------------------------------------------------------------------------ helpers
    def dh_table(self) -> Tensor:
        """The DH table as ``(n, 4)`` columns (a, alpha, d, theta), detached."""
        return torch.stack([self.a, self.alpha, self.d, self.theta], dim=-1).detach()

    def copy(self) -> DHChain:
        """An independent copy (parameters cloned, each as learnable as its original; gradients not shared,
        not compiled)."""
        c = DHChain(
            self.a.detach().clone(),
            self.alpha.detach().clone(),
            self.d.detach().clone(),
            self.theta.detach().clone(),
            joint_types=self.joint_types,
            convention=self.convention,
            base=None if self.base is None else self.base.detach().clone(),
            tool=None if self.tool is None else self.tool.detach().clone(),
            q_limits=None if self.q_limits is None else self.q_limits.clone(),
            name=self.name,
            beta=None if self.beta is None else self.beta.detach().clone(),
        )
        c.metadata = dict(self.metadata)
        c.home, c.planar = None if self.home is None else list(self.home), self.planar
        for key, p in self.named_parameters():
            c.get_parameter(key).requires_grad_(p.requires_grad)
        return c

    # ----------------------------------------------------------------------------------- YAML / dict
    @classmethod
    def from_dict(cls, data: dict, dtype: torch.dtype | None = None, device=None, where: str = "", *,
                  learnable: bool = False) -> DHChain:
        """Chain from a model mapping (YAML schema of :mod:`diffkin.models.io`); values may be expressions."""
        from ..models.io import parse_chain_dict

        kwargs = parse_chain_dict(data, dtype=dtype, device=device, where=where)
        metadata, home, planar = kwargs.pop("metadata"), kwargs.pop("home"), kwargs.pop("planar")
        chain = cls(**kwargs, learnable=learnable)
        chain.metadata, chain.home, chain.planar = metadata, home, planar
        return chain

    def to_dict(self) -> dict:
        """Model mapping (name, convention, joint_types, dh rows, q_limits, base, tool) with plain floats."""
        from ..models.io import chain_to_dict

        return chain_to_dict(self)

    @classmethod
    def from_yaml(cls, path_or_str, dtype: torch.dtype | None = None, device=None, *,
                  learnable: bool = False) -> DHChain:
        """Chain from a YAML file path or a YAML string (see :mod:`diffkin.models` for the schema)."""
        from ..models.io import read_yaml

        data, where = read_yaml(path_or_str)
        return cls.from_dict(data, dtype=dtype, device=device, where=where, learnable=learnable)

    def to_yaml(self, path=None) -> str:
        """YAML text of :meth:`to_dict` (angles that are exact multiples of π/12 written as e.g. ``pi/2``);
        also written to ``path`` if given."""
        from ..models.io import chain_to_yaml

        return chain_to_yaml(self, path)

    def extra_repr(self) -> str:
        return super().extra_repr() + f", convention={self.convention!r}"

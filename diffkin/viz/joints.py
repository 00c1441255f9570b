"""The viewer's joint sliders on the configuration manifold.

One slider per velocity coordinate, in the chain's v order (:class:`~diffkin.kernels.configuration.
ConfigurationSpace`): a revolute or prismatic coordinate (a free joint's x, y, z included) is its value; a
ball joint (and a free joint's rotation) is three sliders, the components of a rotation vector ω relative
to a *reference* configuration q_ref (the last one set from outside: by ``Viewer.set_q``, IK, playback).
The shown configuration is ``chain.integrate(q_ref, v)`` with v holding ω and the scalar sliders' offsets
from q_ref: the quaternion is moved as q_ref ⊗ exp(ω/2) and never edited component by component, so it
stays unit. When q_ref changes the rotation sliders return to 0.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ..kernels.configuration import JOINT_KINDS

__all__: list[str] = []  # used through diffkin.viz.Viewer

_SUFFIX = {"free": ("x", "y", "z", "rx", "ry", "rz"), "ball": ("rx", "ry", "rz"),
           "planar": ("x", "y", "theta")}


@dataclass(frozen=True)
class SliderSpec:
    """One slider: ``label`` with ``unit``, range ``[lo, hi]``, ``v`` its velocity coordinate and ``q`` the
    configuration coordinate of a scalar slider (None for a rotation-vector component)."""

    label: str
    unit: str
    lo: float
    hi: float
    v: int
    q: int | None


def _labels(chain, n_sliders: int) -> list[str]:
    names = list(getattr(chain, "joint_names", None) or [])
    kinds = getattr(chain, "joint_kinds", None)
    out: list[str] = []
    if kinds is not None and len(kinds) == len(names):
        for name, kind in zip(names, kinds):
            k = JOINT_KINDS.get(kind)
            nv = k.nv if k is not None else 1
            out += [f"{name}.{s}" for s in _SUFFIX[kind]] if kind in _SUFFIX else [name] * nv
    elif len(names) == n_sliders:
        out = names
    return out if len(out) == n_sliders else [f"v{i + 1}" for i in range(n_sliders)]


def slider_specs(chain, lo: Tensor, hi: Tensor) -> list[SliderSpec]:
    """The sliders of ``chain`` (v order); ``lo``, ``hi`` ``(nq,)``: finite ranges of the scalar coordinates
    (``chain.lower_upper()``)."""
    motions = chain.configuration_space.motions
    labels = _labels(chain, chain.nv)
    out, iq, iv = [], 0, 0
    for m in motions:
        if m == "S":
            out += [SliderSpec(labels[iv + k], "rad", -math.pi, math.pi, iv + k, None) for k in range(3)]
            iq, iv = iq + 4, iv + 3
        else:
            unit = "rad" if m == "R" else "m"
            out.append(SliderSpec(labels[iv], unit, float(lo[iq]), float(hi[iq]), iv, iq))
            iq, iv = iq + 1, iv + 1
    return out


def slider_values(specs: list[SliderSpec], q: Tensor) -> list[float]:
    """The slider values showing ``q (nq,)`` as the new reference: scalars their value, rotations 0."""
    qs = q.detach().cpu().double().tolist()
    return [qs[s.q] if s.q is not None else 0.0 for s in specs]


def q_of_sliders(chain, q_ref: Tensor, values, specs: list[SliderSpec]) -> Tensor:
    """``chain.integrate(q_ref, v)`` ``(nq,)`` for the slider ``values`` (module doc)."""
    ref = q_ref.detach().cpu().double()
    v = [float(x) - float(ref[s.q]) if s.q is not None else float(x) for s, x in zip(specs, values)]
    v_t = torch.tensor(v, dtype=q_ref.dtype, device=q_ref.device)
    return chain.integrate(q_ref, v_t)

"""The exported low-level distance functions with their input checked once (private).

:mod:`diffkin.collision` exports these wrappers: each validates its arguments with the shared validators
(tensors of float32 / float64, numbers and arrays converted to their dtype, one dtype and device, the
trailing shape of each argument, batch dims that broadcast) and raises the typed errors of
:mod:`diffkin.errors`; then it calls the kernel of :mod:`~diffkin.collision.distances` /
:mod:`~diffkin.collision.boxes` / :mod:`~diffkin.collision.cylinders` / :mod:`~diffkin.collision.convex`
unchanged. The library's own hot
paths call those kernels directly (no check per call). No finiteness check: that would read the values
(a host sync on CUDA).
"""

from __future__ import annotations

import functools
import inspect

import torch

from ..errors import DTypeError, ShapeError
from ..validation import broadcast_batch, shape_str, tensors
from . import boxes, convex, cylinders, distances

V, M, S = (3,), (3, 3), ()  # a point or vector, a rotation matrix, a scalar (radius, offset)
P = (None, 3)  # the vertices of a convex mesh

_SPECS = {
    distances.segment_closest_parameters: dict(a0=V, a1=V, b0=V, b1=V),
    distances.point_segment_parameter: dict(p=V, a=V, b=V),
    distances.sphere_sphere: dict(ca=V, ra=S, cb=V, rb=S),
    distances.sphere_capsule: dict(c=V, r=S, b0=V, b1=V, rb=S),
    distances.capsule_capsule: dict(a0=V, a1=V, ra=S, b0=V, b1=V, rb=S),
    distances.sphere_halfspace: dict(c=V, r=S, n=V, offset=S),
    distances.capsule_halfspace: dict(a0=V, a1=V, r=S, n=V, offset=S),
    boxes.point_box: dict(p=V, center=V, R=M, h=V),
    boxes.sphere_box: dict(c=V, r=S, center=V, R=M, h=V),
    boxes.segment_box: dict(a=V, b=V, c=V, R=M, h=V),
    boxes.capsule_box: dict(a=V, b=V, r=S, c=V, R=M, h=V),
    boxes.box_halfspace: dict(c=V, R=M, h=V, n=V, offset=S),
    boxes.box_box: dict(c1=V, R1=M, h1=V, c2=V, R2=M, h2=V),
    cylinders.point_cylinder: dict(p=V, a=V, b=V, r=S),
    cylinders.sphere_cylinder: dict(c=V, r=S, a=V, b=V, rc=S),
    cylinders.cylinder_halfspace: dict(a=V, b=V, r=S, n=V, offset=S),
    cylinders.capsule_cylinder: dict(a0=V, a1=V, ra=S, b0=V, b1=V, rb=S),
    cylinders.box_cylinder: dict(c=V, R=M, h=V, a=V, b=V, r=S),
    cylinders.cylinder_cylinder: dict(a0=V, a1=V, ra=S, b0=V, b1=V, rb=S),
    convex.convex_halfspace: dict(V=P, n=V, offset=S),
    convex.capsule_convex: dict(a=V, b=V, r=S, V=P),
    convex.box_convex: dict(c=V, R=M, h=V, V=P),
    convex.cylinder_convex: dict(a=V, b=V, r=S, V=P),
    convex.convex_convex: dict(V1=P, V2=P),
}


def _checked(fn):
    spec, sig = _SPECS[fn], inspect.signature(fn)

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            bound = sig.bind(*args, **kwargs)
        except TypeError as e:
            raise ShapeError(f"{fn.__name__}: {e}") from None
        xs = tensors(*((n, bound.arguments.get(n), spec[n]) for n in spec), finite=False)
        broadcast_batch(*((n, x, len(spec[n])) for n, x in zip(spec, xs)))
        return fn(*xs)

    return wrapper


def _index(x, name: str) -> torch.Tensor:
    if not isinstance(x, torch.Tensor) or x.dtype != torch.long or x.ndim != 1:
        got = (f"dtype {x.dtype}, shape {shape_str(x.shape)}" if isinstance(x, torch.Tensor)
               else type(x).__name__)
        raise DTypeError(f"expected {name} as a 1-D torch.long tensor of geom indices, got {got}")
    return x


@functools.wraps(distances.capsule_capsule_pairs)
def capsule_capsule_pairs(a, b, r, i, j, pair_kernel=None):
    a, b, r = tensors(("a", a, (None, 3)), ("b", b, (None, 3)), ("r", r, (None,)), finite=False)
    i, j = _index(i, "i"), _index(j, "j")
    g = a.shape[-2]
    if b.shape[-2] != g or r.shape[-1] != g or i.shape != j.shape:
        raise ShapeError(f"expected a, b (..., G, 3), r (..., G), i and j (P,), got a {shape_str(a.shape)}, "
                         f"b {shape_str(b.shape)}, r {shape_str(r.shape)}, i {shape_str(i.shape)}, "
                         f"j {shape_str(j.shape)}")
    broadcast_batch(("a", a, 2), ("b", b, 2), ("r", r, 1))
    if i.numel() and bool((torch.cat((i, j)) < 0).any() | (torch.cat((i, j)) >= g).any()):
        raise ShapeError(f"expected pair indices i, j in [0, {g}) (G = {g} capsules), got i {i.tolist()}, "
                         f"j {j.tolist()}")
    return distances.capsule_capsule_pairs(a, b, r, i, j, pair_kernel)


# the wrappers, in _SPECS' order
(segment_closest_parameters, point_segment_parameter, sphere_sphere, sphere_capsule, capsule_capsule,
 sphere_halfspace, capsule_halfspace, point_box, sphere_box, segment_box, capsule_box, box_halfspace,
 box_box, point_cylinder, sphere_cylinder, cylinder_halfspace, capsule_cylinder, box_cylinder,
 cylinder_cylinder, convex_halfspace, capsule_convex, box_convex, cylinder_convex,
 convex_convex) = (_checked(fn) for fn in _SPECS)

"""The lean single-call path: FK (2.50) and FK + geometric Jacobian (3.30) of ONE configuration ``q (n,)``.

A batch-1 call through the general dispatch spends most of its time in Python-side checks and tensor
round trips (the fused C pass itself takes about 1 µs for a Panda). :func:`fk` checks what it needs with
plain attribute tests (a plain contiguous CPU tensor of the chain's dtype, shape ``(n,)``, no gradient
wanted), takes the chain's cached :class:`Entry` and makes ONE foreign call, ``dk_fk_one``, on q's own
memory and fresh outputs.

The cache is checked on every call, never trusted: an entry holds the data pointers of every parameter
and buffer it was packed from and a byte snapshot of them (a :class:`Watch`). A tensor replaced, moved
(``.to``), re-materialised or set through ``.data =`` has another pointer; one written in place, with a
version bump (an optimizer step, ``add_`` under ``no_grad``) or without one (``p.data.add_()``, memory
shared with numpy), has other bytes, which ``dk_fk_one`` compares before it computes anything (a few
hundred bytes for a Panda). Either way the entry is remade through the chain's checked state
(:meth:`~diffkin.chain.KinematicChain._state_key`, :meth:`~diffkin.chain.KinematicChain._native_model`).

Anything else (a batch, CUDA, autograd, a traced call, a non-finite q, chains the C kernel does not take)
returns None and the general path serves the call, so results and errors are the general path's.
"""

from __future__ import annotations

import ctypes

import torch
from torch import Tensor

from . import native

__all__ = ["fk", "entry", "Entry", "Watch", "watch"]

_KEY = "_lean_entry"  # the chain's cached Entry, in its instance __dict__ (an attribute read: ~50 ns)
_STALE = native.CONSTANTS["DK_STALE"]
_is_wrapped = torch._C._functorch.is_functorch_wrapped_tensor


_I64, _PTR = ctypes.c_int64, ctypes.c_void_p


_one: tuple = (None, None)  # (the loaded library, its dk_fk_one typed)
_typed: dict = {}  # id of the loaded library -> (dk_unchanged, dk_fk_one, dk_fk_work_bytes), typed once


def _functions():
    """``(dk_unchanged, dk_fk_one, dk_fk_work_bytes)`` of the loaded library (native.available() first).
    dk_fk_one is taken through a ``PyDLL`` handle: it keeps the GIL for its microsecond (no release and
    re-acquire), and its arguments are plain addresses (no per-call type checks of ctypes pointers)."""
    lib = native._lib
    fns = _typed.get(id(lib))
    if fns is None:
        fns = lib.dk_unchanged, ctypes.PyDLL(native._path).dk_fk_one, lib.dk_fk_work_bytes
        for fn, nargs in zip(fns, (1, 5, 1)):
            fn.restype, fn.argtypes = _I64, [_PTR] * nargs
        _typed[id(lib)] = fns
    global _one
    _one = (lib, fns[1])
    return fns


class Watch:
    """A byte snapshot of contiguous CPU tensors at their data pointers: :meth:`unchanged` is False once any
    of their bytes was written (with or without a version bump). The caller checks the pointers are still
    the tensors' (they are in the chain's :meth:`~diffkin.chain.KinematicChain._state_key`). ``work``:
    bytes of ``dk_fk_one``'s work space (plans and scratch kept between calls), 0 for none."""

    __slots__ = ("ptrs", "tensors", "snap", "_keep", "c", "addr")

    def __init__(self, tensors: list[Tensor], work: int = 0):
        self.tensors = tensors  # kept alive: the addresses stay theirs
        self.ptrs = [t.data_ptr() for t in tensors]
        sizes = [t.numel() * t.element_size() for t in tensors]
        self.snap = b"".join(ctypes.string_at(p, n) for p, n in zip(self.ptrs, sizes))
        ptr, size = (_I64 * len(tensors))(*self.ptrs), (_I64 * len(tensors))(*sizes)
        space = ctypes.create_string_buffer(work) if work > 0 else None
        self._keep = (ptr, size, space)
        snap = ctypes.cast(ctypes.c_char_p(self.snap), _PTR).value
        self.c = native.new_struct(native.WatchArgs, n=len(tensors), ptr=ctypes.addressof(ptr),
                                   bytes=ctypes.addressof(size), snap=snap,
                                   work=space and ctypes.addressof(space))
        self.addr = ctypes.addressof(self.c)

    def unchanged(self) -> bool:
        if native._lib is not None:  # loaded (even inside native.disabled()): one memcmp per tensor
            return _functions()[0](self.addr) == 1
        return b"".join(ctypes.string_at(p, t.numel() * t.element_size())
                        for p, t in zip(self.ptrs, self.tensors)) == self.snap

    def __reduce__(self):  # copies and pickles of a chain carry no addresses: the copy makes its own
        return _nothing, ()


def _nothing():
    return None


def _tensors(chain) -> tuple:
    return (*chain._parameters.values(), *chain._buffers.values())


def watch(chain, work: int = 0) -> Watch | None:
    """A :class:`Watch` of every parameter and buffer of ``chain`` when all are contiguous CPU tensors, else
    None (a CUDA chain: reading its bytes would synchronise)."""
    ts = [t for t in _tensors(chain) if t is not None]
    if not all(t.is_cpu and t.is_contiguous() for t in ts):
        return None
    return Watch(ts, work)


class Entry:
    """A chain's cached call state: the packed Args per dtype, the :class:`Watch` of the tensors they were
    packed from (their pointers in ``_tensors`` order, 0 for an unset buffer), output templates, and
    ``extra`` (per-chain state of other lean callers, e.g. the IK solve's, dropped with the entry)."""

    __slots__ = ("ptrs", "topo", "watch", "watch_addr", "args", "extra", "dtype", "n", "T0", "J0", "base")

    def __init__(self, chain, ptrs, args):
        self.ptrs, self.topo, self.args, self.extra = ptrs, chain._topo, args, {}
        self.dtype, self.n, K = chain.dtype, chain.n_joints, chain.n_ends  # read once: properties cost µs
        nv = chain.nv  # Jacobian columns: velocities (a ball joint's quaternion has three)
        shapes = ((4, 4), (6, nv)) if chain.single_end else ((K, 4, 4), (K, 6, nv))
        self.T0, self.J0 = (torch.empty(s, dtype=self.dtype) for s in shapes)  # for empty_like: ~1 µs
        base = args.args[self.dtype]
        self.base = ctypes.addressof(base)  # args keeps it alive
        self.watch = watch(chain, _functions()[2](self.base))
        self.watch_addr = None if self.watch is None else self.watch.addr

    def __reduce__(self):
        return _nothing, ()


def _current(chain, grad: bool) -> Entry | None:
    """The cached entry if the chain's tensors are still at its pointers and none wants a gradient; the
    bytes are not compared here (the caller does: dk_fk_one, or :func:`entry`). None: no entry, or
    not servable now."""
    d = chain.__dict__  # plain reads: nn.Module's attribute lookup costs a microsecond here
    hit, ts = d.get(_KEY), (*d["_parameters"].values(), *d["_buffers"].values())
    if grad:  # a loop, not any(<generator>): half the cost
        for t in ts:
            if t is not None and t.requires_grad:
                return None
    if hit is None:
        return _remade(chain)
    try:
        ptrs = [0 if t is None else t.data_ptr() for t in ts]
    except RuntimeError:  # a tensor without storage (a torch.func wrapper): the general path
        return None
    if ptrs != hit.ptrs or hit.topo is not d["_topo"]:
        return _remade(chain)
    return hit


def _remade(chain) -> Entry | None:
    """A new entry from the chain's checked state (None where the fused kernel cannot serve it)."""
    chain.__dict__.pop(_KEY, None)
    if chain.device.type != "cpu":  # a chain elsewhere: the general path's device error
        return None
    ts = _tensors(chain)
    probe = torch.empty(0, dtype=chain.dtype)
    with torch.no_grad():  # the packed constants are data (a caller may run in grad mode)
        packed = chain._native_model(probe) if chain._state_key() is not None else None
    if packed is None:
        return None
    hit = Entry(chain, [0 if t is None else t.data_ptr() for t in ts], packed)
    if hit.watch is None:
        return None
    chain.__dict__[_KEY] = hit  # a plain attribute, not a module member (not in state_dict)
    return hit


def entry(chain, x: Tensor, grad: bool | None = None) -> Entry | None:
    """The chain's cached :class:`Entry` for a call on the plain CPU tensor ``x``, or None (general path).

    A hit needs every parameter and buffer at the pointer and with the bytes the entry was packed from, and
    no gradient wanted from any of them (``grad``: whether gradients are wanted, default grad mode; False
    for a caller that runs without autograd); a miss re-validates through ``_state_key`` and repacks.
    """
    if torch.compiler.is_compiling() or _is_wrapped(x) or not native.available():
        return None
    hit = _current(chain, torch.is_grad_enabled() if grad is None else grad)
    if hit is not None and not hit.watch.unchanged():
        hit = _remade(chain)
    return hit


def fk(chain, q, jacobian: bool = False, _retry: bool = True):
    """``T (4, 4)`` (``(K, 4, 4)`` for K end links), or ``(T, J (6, nv) / (K, 6, nv))`` with ``jacobian``,
    of one configuration ``q (nq,)``; None when the lean path does not apply (the caller's general path then
    serves the call)."""
    if type(q) is not Tensor or not q.is_cpu or q.ndim != 1 or not q.is_contiguous():
        return None
    grad = torch.is_grad_enabled()
    if (grad and q.requires_grad) or torch.compiler.is_compiling() or _is_wrapped(q) \
            or not native.available():
        return None
    hit = _current(chain, grad)
    if hit is None or q.dtype is not hit.dtype or q.numel() != hit.n:
        return None
    T = torch.empty_like(hit.T0)
    J = torch.empty_like(hit.J0) if jacobian else None
    one = _one[1] if _one[0] is native._lib else _functions()[1]
    status = one(hit.base, hit.watch_addr, q.data_ptr(), T.data_ptr(),
                 J.data_ptr() if jacobian else None)
    if status == _STALE and _retry:  # bytes written in place since the entry was made: remade once
        _remade(chain)
        return fk(chain, q, jacobian, False)
    if status != 0:  # non-finite q (or a failure): the general path's error
        return None
    return (T, J) if jacobian else T

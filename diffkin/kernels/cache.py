"""Model/Data: a chain's derived state in ONE cache object with ONE invalidation rule.

The chain (:class:`~diffkin.chain.KinematicChain`) is the *model*: its parameters, buffers and topology. A
:class:`Data` is everything computed from them that a fast path keeps between calls (Pinocchio's
``Model`` / ``Data`` split): the constant fixed transforms (both forms of
:meth:`~diffkin.chain.KinematicChain._constant_segments`), the packed arrays of the fused C kernel
(:class:`~diffkin.kernels.native.NativeModel`), the lean single-call state (:mod:`diffkin.kernels.single`:
the C argument block, output templates, ``dk_fk_one``'s work space), the zero flags of the base and tool
corrections and, in :attr:`Data.extra`, what other fast paths derive from them (the IK solve's prepared
arguments, the centre-of-mass pack, the all-frames pack of the collision model). A chain holds at most
one Data (``chain.__dict__["_model_data"]``, a plain attribute: not in ``state_dict``, dropped by copies and
pickles); a stale Data is replaced whole, so nothing derived can outlive the values it came from.

**The rule** (:meth:`Data.current`): a Data is current while the chain's topology is the same object and
every parameter and buffer is at the data pointer and holds the contents it was made from — contents
compared byte for byte on CPU, by ``_version`` on other devices (reading their bytes would synchronise).

The byte comparison is what sees a write through ``param.data`` (``p.data.add_()``, memory shared with
numpy): ``.data`` hands out a tensor with its own version counter, so such a write bumps no version. A
tensor replaced (``setattr``, a new ``nn.Parameter``, ``.data =``), moved or converted (``.to``,
``.double()``) or re-materialised has another pointer; one updated in place (an optimizer step,
``load_state_dict``'s copy, ``add_``) has other bytes. The Data keeps every tensor it was made from alive,
so a pointer can never be reused by another tensor while the Data lives. On CUDA a ``.data`` write is not
seen (no version, no byte read without a host sync): call :func:`drop` after one.

The lean paths evaluate the same rule in two halves: the pointers in Python (:func:`pointers`), the bytes
in C (``dk_fk_one`` / ``dk_solve_one`` / ``dk_velocity_step`` compare the :class:`Watch` snapshot before
they compute, and answer ``DK_STALE``); on ``DK_STALE`` the caller drops the Data (:func:`drop`).

This module reads the chain only through its ``__dict__`` and two methods (``_constant_segments``, the
properties ``single_end`` / ``n_ends`` / ``nv``): the kernels never import the chain.
"""

from __future__ import annotations

import ctypes
import itertools
import threading

import torch
from torch import Tensor, nn

from . import native

__all__ = ["Data", "Watch", "current", "drop", "filled", "pointers", "KEY"]

KEY = "_model_data"  # the chain's Data, in its instance __dict__ (a plain read: ~50 ns)
_GENERATION = itertools.count(1)  # unique over all chains: a Data's generation is a cache key elsewhere
_I64, _PTR = ctypes.c_int64, ctypes.c_void_p
_is_wrapped = torch._C._functorch.is_functorch_wrapped_tensor
_unchanged: tuple = (None, None)  # (the loaded library, its dk_unchanged typed)
_MAKING = threading.Lock()  # held while a chain's new Data is made and stored


def _dk_unchanged():
    global _unchanged
    lib = native._lib
    if _unchanged[0] is not lib:
        fn = lib.dk_unchanged
        fn.restype, fn.argtypes = _I64, [_PTR]
        _unchanged = (lib, fn)
    return _unchanged[1]


class Watch:
    """A byte snapshot of contiguous CPU tensors at their data pointers: :meth:`unchanged` is False once any
    of their bytes was written (with or without a version bump). The caller checks the pointers are still
    the tensors' (:meth:`Data.current`). :meth:`give_work` attaches ``dk_fk_one``'s work space (plans and
    scratch kept between calls)."""

    __slots__ = ("ptrs", "tensors", "snap", "_keep", "c", "addr")

    def __init__(self, tensors: list[Tensor]):
        self.tensors = tensors  # kept alive: the addresses stay theirs
        self.ptrs = [t.data_ptr() for t in tensors]
        sizes = [t.numel() * t.element_size() for t in tensors]
        self.snap = b"".join(ctypes.string_at(p, n) for p, n in zip(self.ptrs, sizes))
        ptr, size = (_I64 * len(tensors))(*self.ptrs), (_I64 * len(tensors))(*sizes)
        self._keep = (ptr, size)
        snap = ctypes.cast(ctypes.c_char_p(self.snap), _PTR).value
        self.c = native.new_struct(native.WatchArgs, n=len(tensors), ptr=ctypes.addressof(ptr),
                                   bytes=ctypes.addressof(size), snap=snap, work=None)
        self.addr = ctypes.addressof(self.c)

    def give_work(self, nbytes: int) -> None:
        """Attach a work space of ``nbytes`` for ``dk_fk_one`` (once; before any call used this watch)."""
        if nbytes > 0 and not self.c.work:
            space = ctypes.create_string_buffer(nbytes)
            self._keep = (*self._keep, space)
            self.c.work = ctypes.addressof(space)

    def unchanged(self) -> bool:
        if native._lib is not None:  # loaded (even inside native.disabled()): one memcmp per tensor
            return _dk_unchanged()(self.addr) == 1
        return b"".join(ctypes.string_at(p, t.numel() * t.element_size())
                        for p, t in zip(self.ptrs, self.tensors)) == self.snap

    def __reduce__(self):  # copies and pickles of a chain carry no addresses: the copy makes its own
        return _nothing, ()


def _nothing():
    return None


def _tensors(chain) -> tuple:
    d = chain.__dict__
    return (*d["_parameters"].values(), *d["_buffers"].values())


def pointers(ts) -> list[int]:
    """The data pointers of ``ts`` (0 for an unset buffer); raises RuntimeError for a tensor without
    storage (a torch.func wrapper)."""
    return [0 if t is None else t.data_ptr() for t in ts]


def _plain(t: Tensor) -> bool:
    """An ordinary tensor (not a torch.func / compile wrapper or a subclass), whose values can be read."""
    return type(t) in (Tensor, nn.Parameter) and not _is_wrapped(t)


class Data:
    """The derived state of one chain at one state of its parameters and buffers (module doc).

    Slots filled on first use: :attr:`constants` (``(per_joint, stacked)`` Segments), :attr:`native` (the
    :class:`~diffkin.kernels.native.NativeModel`), the lean call state (:meth:`lean`: :attr:`base` the
    address of the packed ``dk_args`` of the chain's dtype, :attr:`watch_addr`, output templates
    :attr:`T0` / :attr:`J0`), :attr:`zero` (per ``"base"`` / ``"tool"``: whether that correction is
    exactly zero) and :attr:`extra` (other fast paths' derived state, by their own keys: :meth:`derived`).

    The slots of derived objects (:attr:`constants`, :attr:`native`, the lean state, :meth:`derived` entries
    of :attr:`extra`) are filled once, under the Data's lock: calls from several threads share one Data, and
    C calls hold plain addresses into what the slots keep alive (the packed ``dk_args``, the watch), so a
    slot made twice and replaced would free memory another thread's call is reading. Plain values (the
    :attr:`zero` flags, a recognised closed-form family) may be found twice by racing threads, the same
    value each time."""

    __slots__ = ("generation", "tensors", "ptrs", "versions", "topo", "dtype", "device", "watch", "copies",
                 "constants", "native", "base", "watch_addr", "n", "T0", "J0", "zero", "extra", "_lock")

    def __init__(self, ts: tuple, topo, dtype: torch.dtype, device: torch.device):
        self.generation = next(_GENERATION)
        self.tensors, self.topo, self.dtype, self.device = ts, topo, dtype, device  # tensors kept alive
        self.ptrs = pointers(ts)
        self.versions = [None if t is None else t._version for t in ts]
        live = [t for t in ts if t is not None]
        cpu = [t for t in live if t.is_cpu]
        flat = [t for t in cpu if t.is_contiguous()]
        self.watch = Watch(flat) if flat and len(cpu) == len(live) else None
        # a non-contiguous CPU tensor: its values compared as a copy (rare: the chain makes them contiguous)
        self.copies = [(t, t.detach().clone()) for t in cpu if not t.is_contiguous()] \
            if self.watch is not None else []
        self.constants = self.native = self.base = self.watch_addr = self.T0 = self.J0 = None
        self.n = 0
        self.zero: dict[str, bool] = {}
        self.extra: dict = {}
        self._lock = threading.RLock()  # re-entrant: lean() fills native, which fills constants

    def current(self, ts: tuple, topo) -> bool:
        """THE rule: the same topology object, every tensor at the same pointer, and unchanged contents
        (bytes on CPU, ``_version`` elsewhere). Raises RuntimeError for a tensor without storage."""
        if topo is not self.topo or pointers(ts) != self.ptrs:
            return False
        if self.watch is None:
            return [None if t is None else t._version for t in ts] == self.versions
        return self.watch.unchanged() and all(torch.equal(t, c) for t, c in self.copies)

    # ------------------------------------------------------------------------------------------ slots
    def segments(self, chain) -> tuple:
        """``(per_joint, stacked)``: the chain's constant fixed transforms (made once per Data)."""
        if self.constants is None:
            with self._lock:
                if self.constants is None:
                    self.constants = chain._constant_segments()
        return self.constants

    def native_model(self, chain) -> native.NativeModel:
        """The packed constants of the fused C kernel (made once per Data; the library must be loaded)."""
        if self.native is None:
            with self._lock:
                if self.native is None:
                    self.native = native.NativeModel(self.topo, self.segments(chain)[0])
        return self.native

    def derived(self, key, make):
        """``extra[key]``, made by ``make()`` the first time (:func:`filled` under the Data's lock)."""
        return filled(self.extra, key, self._lock, make)

    def lean(self, chain) -> Data | None:
        """This Data with its single-call state filled (the packed ``dk_args`` of the chain's dtype, the
        watch with ``dk_fk_one``'s work space, output templates), or None where the lean paths cannot
        serve the chain (not every tensor a contiguous CPU one, or the library not loaded)."""
        if self.base is not None:
            return self
        if self.watch is None or self.copies or self.device.type != "cpu" or not native.available():
            return None
        with self._lock:
            return self if self.base is not None else self._fill_lean(chain)

    def _fill_lean(self, chain) -> Data:
        with torch.no_grad():  # the packed constants are data (a caller may run in grad mode)
            args = self.native_model(chain).args[self.dtype]
        self.n, K, nv = chain.n_joints, chain.n_ends, chain.nv  # read once: properties cost µs
        shapes = ((4, 4), (6, nv)) if chain.single_end else ((K, 4, 4), (K, 6, nv))
        self.T0, self.J0 = (torch.empty(s, dtype=self.dtype) for s in shapes)  # for empty_like: ~1 µs
        base = ctypes.addressof(args)  # self.native keeps it alive
        lib = native._lib
        lib.dk_fk_work_bytes.restype, lib.dk_fk_work_bytes.argtypes = _I64, [_PTR]
        self.watch.give_work(int(lib.dk_fk_work_bytes(base)))
        self.watch_addr, self.base = self.watch.addr, base
        return self

    def __reduce__(self):  # copies and pickles of a chain carry no addresses: the copy makes its own
        return _nothing, ()


def current(chain, grad: bool | None = None) -> Data | None:
    """The chain's current :class:`Data` by the rule, made anew when stale (or never made); None where the
    values cannot be read as constants now: traced (``torch.compile``), a torch.func wrapper or tensor
    subclass among the parameters and buffers, or a gradient wanted from one of them (``grad``: whether
    gradients are wanted, default grad mode)."""
    if torch.compiler.is_compiling():  # traced: parameters are graph inputs, never constants
        return None
    d = chain.__dict__
    ts = (*d["_parameters"].values(), *d["_buffers"].values())
    if torch.is_grad_enabled() if grad is None else grad:
        for t in ts:
            if t is not None and t.requires_grad:
                return None
    data = d.get(KEY)
    if data is not None:
        try:
            if data.current(ts, d["_topo"]):
                return data
        except RuntimeError:  # a tensor without storage (a torch.func wrapper)
            return None
    for t in ts:
        if t is not None and not _plain(t):
            return None
    with _MAKING:  # one new Data however many threads found the old one stale (or none)
        data = d.get(KEY)
        if data is None or not data.current(ts, d["_topo"]):
            mask = d["_buffers"]["revolute_mask"]
            data = d[KEY] = Data(ts, d["_topo"], mask.dtype, mask.device)
    return data


def filled(cache: dict, key, lock, make):
    """``cache[key]``, made by ``make()`` the first time, under ``lock`` (once, whichever thread asks first:
    the others wait and get the same object, so an address into it stays valid while the cache holds it). A
    ``make()`` that answers None stores nothing (asked again next time); one that raises stores nothing."""
    value = cache.get(key)
    if value is None:
        with lock:
            value = cache.get(key)
            if value is None:
                value = make()
                if value is not None:
                    cache[key] = value
    return value


def drop(chain) -> None:
    """Forget the chain's Data (after a C entry point answered ``DK_STALE``, or a ``.data`` write on CUDA):
    the next call makes a new one."""
    chain.__dict__.pop(KEY, None)

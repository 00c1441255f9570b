"""Model/Data (diffkin/kernels/cache.py): every fast path sees every change of every parameter and buffer.

For a DH Panda, a URDF Panda and an MJCF floating-base leg of Menagerie's G1, every float parameter and
buffer that the kinematics read is changed in each way a user can change it (in place with ``add_``, through
``.data`` (no version bump), replaced by ``setattr`` / a new ``nn.Parameter``, ``.data =`` a new tensor,
``load_state_dict``, a move to the ``meta`` device and back (new storage, as a device move makes), and a
dtype move), after every path has run and cached what it caches. Then every path (single-call FK and FK +
Jacobian, native batch FK and Jacobian, the torch constant paths small and large, one-target and batched
``ik.solve``, the native centre of mass) must give what a chain that never ran gives with the same values.
A cache that ignores one of the ways returns the old geometry and fails here."""

from __future__ import annotations

import copy
from pathlib import Path

import pytest
import torch
from torch import nn

from diffkin import ik, models
from diffkin.kernels import native
from diffkin.models import from_mjcf

G1 = Path(__file__).parent / "data" / "mjcf" / "unitree_g1" / "g1.xml"
STRUCTURE = {"revolute_mask", "_joint_revolute", "qpos0"}  # structure (or unread): not values to change
WAYS = ("add_", "data", "setattr", "data_assign", "load_state_dict", "meta")
# the default run's tensors (None: all); the extended run changes every one of every chain
FAST = {"panda": None, "panda_urdf": ("origin_rpy", "axis"),
        "g1_leg": ("body_quat", "q_limits", "link_masses")}


def _make(name: str) -> nn.Module:
    if name == "g1_leg":
        return from_mjcf(G1, "left_ankle_roll_link", dtype=torch.float64)
    return models.load(name, dtype=torch.float64)


@pytest.fixture(scope="module", params=["panda", "panda_urdf", "g1_leg"])
def proto(request):
    chain = _make(request.param)
    g = torch.Generator().manual_seed(3)
    qb = chain.random_configuration(40, generator=g)
    with torch.no_grad():
        Tb = chain.forward_kinematics(qb[:4])
    return chain, qb, Tb, request.param


def _tensors(chain) -> dict:
    return {**{k: p for k, p in chain._parameters.items() if p is not None},
            **{k: b for k, b in chain._buffers.items() if b is not None}}


def _changed(name: str, t: torch.Tensor) -> torch.Tensor:
    """New values for ``name`` that change what the kinematics (or the solve, or the centre of mass) give."""
    new = t.detach().clone()
    if name == "q_limits":  # the last joint confined to a narrow range inside its own
        lo, hi = new[-1].clamp(-1.0, 1.0)
        mid = float(0.5 * (lo + hi))
        new[-1] = torch.tensor([mid, mid + 0.01], dtype=new.dtype)
        return new
    if name == "link_masses":  # not a common factor: the weights m_i / M change
        return new * torch.linspace(0.5, 2.0, new.numel(), dtype=new.dtype)
    return new + 0.03


def _cat(*xs) -> torch.Tensor:
    return torch.cat([x.flatten() for x in xs])


# every path, each a function of (chain, q (B, nq), T (4, 4, 4)) in the chain's dtype
PATHS = {
    "fk_one": lambda c, q, T: c.forward_kinematics(q[0]),  # kernels/single.py: dk_fk_one
    "fkj_one": lambda c, q, T: _cat(*c.forward_kinematics_and_jacobian(q[1])),
    "fk_native": lambda c, q, T: c.forward_kinematics(q),  # the fused C pass
    "jac_native": lambda c, q, T: c.geometric_jacobian(q),
    "fk_small": lambda c, q, T: _torch(c.forward_kinematics, q[:3]),  # torch kernels, constant transforms
    "fk_large": lambda c, q, T: _torch(c.forward_kinematics, q),
    "fkj_small": lambda c, q, T: _cat(*_torch(c.forward_kinematics_and_jacobian, q[:3])),
    "com": lambda c, q, T: c.center_of_mass(q),  # the native pass with the masses' pack
    "ik_one": lambda c, q, T: ik.solve(c, T[0], seed=0).q,  # dk_solve_one
    "ik_batch": lambda c, q, T: ik.solve(c, T, seed=0).q,  # dk_solve
}


def _torch(fn, q):
    with native.disabled():
        return fn(q)


def _paths(chain) -> list[str]:
    skip = {"com"} if getattr(chain, "link_masses", None) is None else set()
    if chain.dtype != torch.float64:
        skip |= {"ik_one", "ik_batch"}
    return [k for k in PATHS if k not in skip]


def _run(chain, path: str, qb, Tb) -> torch.Tensor:
    q, T = qb.to(chain.dtype), Tb.to(chain.dtype)
    if path.startswith("ik"):
        return PATHS[path](chain, q, T)
    with torch.no_grad():
        return PATHS[path](chain, q, T)


def _outputs(chain, qb, Tb) -> dict:
    """What every path gives (float64 inputs converted to the chain's dtype)."""
    return {k: _run(chain, k, qb, Tb) for k in _paths(chain)}


def _fresh(proto_chain, chain) -> nn.Module:
    """A chain that never ran, with ``chain``'s values (and dtype)."""
    ref = copy.deepcopy(proto_chain).to(chain.dtype)
    ref.__dict__.pop("_model_data", None)
    with torch.no_grad():
        for name, t in _tensors(chain).items():
            target = ref._parameters if name in ref._parameters else ref._buffers
            target[name] = (nn.Parameter(t.detach().clone(), requires_grad=False) if target is ref._parameters
                            else t.detach().clone())
    return ref


def _compare(got: dict, want: dict, where: str) -> None:
    assert got.keys() == want.keys()
    for k in want:
        assert got[k].dtype == want[k].dtype, f"{where}: {k} dtype"
        tol = 1e-9 if want[k].dtype == torch.float64 else 1e-5
        assert torch.allclose(got[k], want[k], atol=tol, rtol=0), f"{where}: {k} is stale"


def _apply(chain, way: str, name: str, new: torch.Tensor) -> None:
    t = _tensors(chain)[name]
    is_param = name in chain._parameters
    step = torch.where(new == t.detach(), 0.0, new - t.detach())  # (±inf limits stay: no inf - inf)
    if way == "add_":
        with torch.no_grad():
            t.add_(step)
    elif way == "data":  # no version bump
        t.data.add_(step)
    elif way == "setattr":
        setattr(chain, name, nn.Parameter(new.clone(), requires_grad=False) if is_param else new.clone())
    elif way == "data_assign":
        t.data = new.clone()
    elif way == "load_state_dict":
        sd = chain.state_dict()
        sd[name] = new
        chain.load_state_dict(sd)
    elif way == "meta":  # new storage everywhere (as a device move makes), values written back
        saved = {k: v.detach().clone() for k, v in _tensors(chain).items()}
        saved[name] = new
        chain.to("meta")
        chain.to_empty(device="cpu")
        with torch.no_grad():
            for k, v in _tensors(chain).items():
                v.copy_(saved[k])


@pytest.mark.parametrize("sweep", ["fast", pytest.param("full", marks=pytest.mark.extended)])
@pytest.mark.parametrize("way", WAYS)
def test_every_path_sees_every_change(proto, way, sweep):
    """Each path on its own (a path that ran first could otherwise renew the Data for the others): a chain
    on which only this path has run, the change, the path again."""
    base, qb, Tb, model = proto
    names = [k for k, t in _tensors(base).items() if k not in STRUCTURE and t.is_floating_point()
             and t.numel() > 0 and (k != "_offsets" or base._has_offsets)]  # (all zero: never read)
    assert len(names) >= 6
    if sweep == "fast" and FAST[model] is not None:
        names = [k for k in names if k in FAST[model]]
    if way == "load_state_dict":
        names = [k for k in names if k in base.state_dict()]
    before = _outputs(copy.deepcopy(base), qb, Tb)
    for name in names:
        want = None
        for path in _paths(base):
            chain = copy.deepcopy(base)
            _run(chain, path, qb, Tb)  # this path has run: what it caches is filled
            _apply(chain, way, name, _changed(name, _tensors(chain)[name]))
            if want is None:
                want = _outputs(_fresh(base, chain), qb, Tb)
                assert any(not torch.equal(before[k], want[k]) for k in want), f"{name}: no path shows it"
            _compare({path: _run(chain, path, qb, Tb)}, {path: want[path]}, f"{way} {name}")


def test_every_path_sees_a_dtype_move(proto):
    """``.float()`` and back ``.double()`` (float32-rounded values), each path on its own."""
    base, qb, Tb, _ = proto
    for path in _paths(base):
        chain = copy.deepcopy(base)
        _run(chain, path, qb, Tb)
        for move in ("float", "double"):
            getattr(chain, move)()
            if path in _paths(chain):
                want = _run(_fresh(base, chain), path, qb, Tb)
                _compare({path: _run(chain, path, qb, Tb)}, {path: want}, f"{move}()")


def test_one_data_per_chain_and_a_new_one_per_change(proto):
    """The chain keeps one Data; a write through ``.data`` replaces it (the rule), a call without a change
    keeps it (no repacking on every call)."""
    base, qb, Tb, _ = proto
    chain = copy.deepcopy(base)
    _outputs(chain, qb, Tb)
    first = chain.__dict__["_model_data"]
    _outputs(chain, qb, Tb)
    assert chain.__dict__["_model_data"] is first
    p = next(p for p in chain.parameters() if p.numel())
    p.data.add_(0.01)
    _outputs(chain, qb, Tb)
    assert chain.__dict__["_model_data"] is not first

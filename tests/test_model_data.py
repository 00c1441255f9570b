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
    return chain, qb, Tb


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


def _outputs(chain, qb, Tb) -> dict:
    """What every path gives (float64 inputs converted to the chain's dtype)."""
    q, T = qb.to(chain.dtype), Tb.to(chain.dtype)
    out = {}
    with torch.no_grad():
        out["fk_one"] = chain.forward_kinematics(q[0])  # kernels/single.py: dk_fk_one
        out["fkj_one"] = torch.cat([x.flatten() for x in chain.forward_kinematics_and_jacobian(q[1])])
        out["fk_native"] = chain.forward_kinematics(q)  # the fused C pass
        out["jac_native"] = chain.geometric_jacobian(q)
        with native.disabled():  # the torch kernels on the constant transforms
            out["fk_small"] = chain.forward_kinematics(q[:3])
            out["fk_large"] = chain.forward_kinematics(q)
            out["fkj_small"] = torch.cat([x.flatten() for x in chain.forward_kinematics_and_jacobian(q[:3])])
        if getattr(chain, "link_masses", None) is not None:
            out["com"] = chain.center_of_mass(q)  # the native pass with the masses' pack
    if chain.dtype == torch.float64:
        out["ik_one"] = ik.solve(chain, T[0], seed=0).q  # dk_solve_one
        out["ik_batch"] = ik.solve(chain, T, seed=0).q  # dk_solve
    return out


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


@pytest.mark.parametrize("way", WAYS)
def test_every_path_sees_every_change(proto, way):
    base, qb, Tb = proto
    names = [k for k, t in _tensors(base).items() if k not in STRUCTURE and t.is_floating_point()
             and t.numel() > 0 and (k != "_offsets" or base._has_offsets)]  # (all zero: never read)
    if way == "load_state_dict":
        names = [k for k in names if k in base.state_dict()]
    assert len(names) >= 6
    for name in names:
        chain = copy.deepcopy(base)
        before = _outputs(chain, qb, Tb)  # every path has run: every cache is filled
        _apply(chain, way, name, _changed(name, _tensors(chain)[name]))
        want = _outputs(_fresh(base, chain), qb, Tb)
        assert any(not torch.equal(before[k], want[k]) for k in want), f"{name}: the change shows nowhere"
        _compare(_outputs(chain, qb, Tb), want, f"{way} {name}")


def test_every_path_sees_a_dtype_move(proto):
    base, qb, Tb = proto
    chain = copy.deepcopy(base)
    _outputs(chain, qb, Tb)
    chain.float()
    _compare(_outputs(chain, qb, Tb), _outputs(_fresh(base, chain), qb, Tb), "float()")
    chain.double()  # back: float32-rounded values in float64
    _compare(_outputs(chain, qb, Tb), _outputs(_fresh(base, chain), qb, Tb), "double()")


def test_one_data_per_chain_and_a_new_one_per_change(proto):
    """The chain keeps one Data; a write through ``.data`` replaces it (the rule), a call without a change
    keeps it (no repacking on every call)."""
    base, qb, Tb = proto
    chain = copy.deepcopy(base)
    _outputs(chain, qb, Tb)
    first = chain.__dict__["_model_data"]
    _outputs(chain, qb, Tb)
    assert chain.__dict__["_model_data"] is first
    p = next(p for p in chain.parameters() if p.numel())
    p.data.add_(0.01)
    _outputs(chain, qb, Tb)
    assert chain.__dict__["_model_data"] is not first

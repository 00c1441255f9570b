"""The public API against a checked-in list (tests/data/public_api.txt), and the one result convention.

An accidental rename or removal of an exported name, or a changed signature of a main entry point, fails
``test_public_api_matches_the_list``. A deliberate change regenerates the list and shows in the diff:

    python -m tests.test_public_api      # rewrites tests/data/public_api.txt

The renames of issue #30 item 15 (``docs/api/deprecated.md``) kept no alias: 0.1 never shipped a release.
"""

from __future__ import annotations

import importlib
import inspect
import pkgutil
from pathlib import Path

import pytest
import torch

import diffkin
from diffkin import ik, models
from diffkin.chain import KinematicChain
from diffkin.errors import ShapeError

LIST = Path(__file__).parent / "data" / "public_api.txt"
F64 = torch.float64

#: the main entry points whose signatures are part of the list (names, positions, defaults)
ENTRY_POINTS = [
    "diffkin.forward_kinematics_and_jacobian", "diffkin.geometric_jacobian",
    "diffkin.jacobian.analytical_jacobian", "diffkin.ik.solve", "diffkin.ik.optimize", "diffkin.ik.clik",
    "diffkin.ik.closed_form", "diffkin.ik.dls_step", "diffkin.ik.velocity_step", "diffkin.ik.solve_velocity",
    "diffkin.ik.joint_trajectory_from_poses", "diffkin.models.load", "diffkin.models.from_urdf",
    "diffkin.calibration.calibrate", "diffkin.calibration.calibrate_batch",
]
#: chain methods whose signatures are in the list
CHAIN_METHODS = ["forward_kinematics", "forward_kinematics_and_jacobian", "geometric_jacobian",
                 "analytical_jacobian", "compile_fk", "uncompile_fk", "random_configuration", "within_limits"]


def _modules() -> list[str]:
    """diffkin, every module it exports and every subpackage, those with an ``__all__``."""
    names = {"diffkin"}
    names |= {f"diffkin.{n}" for n in diffkin.__all__ if inspect.ismodule(getattr(diffkin, n))}
    names |= {f"diffkin.{m.name}" for m in pkgutil.iter_modules(diffkin.__path__) if m.ispkg}
    return sorted(n for n in names if hasattr(importlib.import_module(n), "__all__"))


def _resolve(path: str):
    module, _, name = path.rpartition(".")
    return getattr(importlib.import_module(module), name)


def current_api() -> list[str]:
    lines = []
    for m in _modules():
        lines += [f"name {m}.{n}" for n in sorted(importlib.import_module(m).__all__)]
    lines += [f"signature {p}{inspect.signature(_resolve(p))}" for p in ENTRY_POINTS]
    lines += [f"signature KinematicChain.{n}{inspect.signature(getattr(KinematicChain, n))}"
              for n in CHAIN_METHODS]
    return lines


def test_public_api_matches_the_list():
    want = LIST.read_text().splitlines()
    got = current_api()
    removed, added = sorted(set(want) - set(got)), sorted(set(got) - set(want))
    assert not removed and not added, (
        f"the public API changed: removed or changed {removed}, added {added}; if deliberate, run "
        "`python -m tests.test_public_api` and commit tests/data/public_api.txt")


def test_the_list_covers_the_subpackages():
    lines = LIST.read_text().splitlines()
    names = {line.split()[1].rsplit(".", 1)[0] for line in lines if line.startswith("name")}
    assert {"diffkin", "diffkin.ik", "diffkin.calibration", "diffkin.models", "diffkin.jacobian",
            "diffkin.redundancy", "diffkin.manipulability", "diffkin.statics"} <= names


# ------------------------------------------------------------------------------------ the renamed names
@pytest.fixture(scope="module")
def panda():
    return models.load("panda", dtype=F64)


@pytest.fixture(scope="module")
def q(panda):
    return panda.random_configuration(5, generator=torch.Generator().manual_seed(0))


def test_removed_names_are_gone(panda, q):
    """No alias kept for the renames (never released): the old name is an AttributeError/TypeError."""
    with pytest.raises(AttributeError):
        diffkin.jacobian.pinv  # noqa: B018  (its one home is diffkin.redundancy)
    with pytest.raises(ImportError):
        from diffkin.jacobian import manipulability  # noqa: F401
    assert not hasattr(panda, "fk_jacobian") and not hasattr(panda, "uncompile")
    assert KinematicChain.compile is torch.nn.Module.compile  # torch's, no longer shadowed
    # the method and the module function: one computation, with or without options
    T2, J2 = panda.forward_kinematics_and_jacobian(q)
    T3, J3 = diffkin.forward_kinematics_and_jacobian(panda, q, frame="ee")
    T4, J4 = panda.forward_kinematics_and_jacobian(q, frame="ee")
    torch.testing.assert_close(J3, J4, rtol=0, atol=0)
    assert not torch.allclose(J3, J2)  # the option took effect


def test_nn_module_compile_works_on_a_chain(panda, q):
    """``chain.compile()`` is ``nn.Module.compile``: it compiles ``forward`` in place (lazily; the eager
    backend keeps the test fast) and the compiled module returns the same poses."""
    chain = models.load("panda", dtype=F64)
    assert chain.compile(backend="eager") is None and chain._compiled_call_impl is not None
    torch.testing.assert_close(chain(q), panda.forward_kinematics(q), rtol=0, atol=1e-12)
    assert chain._compiled_fk is None  # compile_fk's fast path is another, opt-in thing
    assert chain.compile_fk()._compiled_fk is not None and chain.uncompile_fk()._compiled_fk is None


def test_closed_form_success():
    ur5 = models.load("ur5", dtype=F64)
    T = ur5.forward_kinematics(ur5.random_configuration(4, generator=torch.Generator().manual_seed(1)))
    sol = ik.closed_form(ur5, T)
    assert sol.success.dtype == torch.bool and sol.success.any(-1).all()
    assert not hasattr(sol, "valid")
    q_, ok = sol  # still a 2-tuple
    assert ok is sol.success
    with pytest.raises(TypeError):
        ik.closed_form(ur5, T=T)


def _planar():
    return models.load("three_link_planar", dtype=F64)


def _clik_inputs(chain, poses: bool):
    q0 = torch.tensor([0.3, 0.5, -0.4], dtype=F64)
    T = chain.forward_kinematics(torch.tensor([0.5, 0.2, -0.1], dtype=F64)).expand(20, 4, 4)
    return q0, (T if poses else T[..., :3, 3])


@pytest.mark.parametrize("form", ["tuple", "pose tensor", "callable"])
def test_clik_old_argument_order_is_a_typed_error(form):
    chain = _planar()
    q0, x = _clik_inputs(chain, poses=True)
    target = {"tuple": (x,), "pose tensor": x, "callable": lambda t: (x[0], None)}[form]
    kw = {"algorithm": "dls", "orientation": None, "steps": 19} if form == "callable" else {
        "algorithm": "dls", "orientation": None}
    ik.clik(chain, target, q0, 0.01, **kw)  # the one order
    with pytest.raises(ShapeError, match=r"clik\(chain, T_target, q0"):
        ik.clik(chain, q0, target, 0.01, **kw)
    with pytest.raises(TypeError):
        ik.clik(chain, q0, target=target, dt=0.01, **kw)


def test_clik_position_targets_take_the_one_order():
    chain = _planar()  # n = 3: a position target (S, 3) and a batch of q0 (B, 3) share the trailing size
    q0, p = _clik_inputs(chain, poses=False)
    kw = {"algorithm": "dls", "orientation": None}
    new = ik.clik(chain, p, q0, 0.01, **kw)
    with pytest.raises(ShapeError, match="no time axis"):  # a 1-D q0 first
        ik.clik(chain, q0, p, 0.01, **kw)
    both = ik.clik(chain, p, q0.expand(20, 3), 0.01, **kw)  # same trailing size: no guessing, as written
    torch.testing.assert_close(both.q, new.q.expand_as(both.q), rtol=0, atol=1e-12)  # batched kernels


def test_clik_result_success():
    chain = _planar()
    q0, x = _clik_inputs(chain, poses=True)
    res = ik.clik(chain, (x,), q0, 0.01, algorithm="dls", orientation="axis_angle", K=50.0)
    t, q, qdot, e, pe, oe, poses = res  # still the 7-tuple
    ok = (pe[..., -1] <= 1e-4) & (oe[..., -1] <= 1e-3)
    assert res.success.shape == res.q.shape[:-2] and torch.equal(res.success, ok)
    tight = ik.clik(chain, (x,), q0, 0.01, algorithm="dls", orientation="axis_angle", K=50.0,
                    position_tolerance=1e-300, orientation_tolerance=1e-300)
    assert pe[..., -1] > 1e-300 and not tight.success  # the tolerance is the one given
    short = ik.clik(chain, (x[:2],), q0, 0.01, algorithm="dls", orientation="axis_angle", K=1.0)
    assert not short.success  # two steps at a low gain do not reach the target


def test_joint_trajectory_from_poses_takes_T_target():
    chain = _planar()
    q0, x = _clik_inputs(chain, poses=True)
    new = ik.joint_trajectory_from_poses(chain, x[:5], q0)
    kw = ik.joint_trajectory_from_poses(chain, T_target=x[:5], q0=q0)
    torch.testing.assert_close(kw.q, new.q, rtol=0, atol=0)
    with pytest.raises(TypeError):
        ik.joint_trajectory_from_poses(chain, T_traj=x[:5], q0=q0)


if __name__ == "__main__":
    LIST.write_text("\n".join(current_api()) + "\n")
    print(f"wrote {LIST} ({len(current_api())} lines)")

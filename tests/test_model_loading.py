"""diffkin.models.load_chain, the one loader (CLI, calibrate_from_files, envs): every source kind gives the
chain the format's own builder gives (same FK), in the dtype and device asked for; errors name the source."""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from diffkin import models
from diffkin.chain import KinematicChain
from diffkin.errors import DeviceError, ModelError

DATA = Path(__file__).parent / "data"
FR3 = DATA / "urdf" / "fr3.urdf"
PANDA_XML = DATA / "mjcf" / "franka_emika_panda" / "panda.xml"
YAML = Path(models.__file__).parent / "data" / "ur5.yaml"
PANDA_YAML = Path(models.__file__).parent / "data" / "panda.yaml"


def _q(chain, n=5):
    return chain.random_configuration(n, generator=torch.Generator().manual_seed(0))


def _dh_table_fk(yaml_path: Path, q: np.ndarray) -> np.ndarray:
    """(n, 4, 4) from the YAML file read with PyYAML and the DH products written out here: standard DH
    (eq. 2.52, A = Rz(theta) Tz(d) Tx(a) Rx(alpha)) or modified DH (Craig, A = Rx(alpha) Tx(a) Rz(theta)
    Tz(d))."""
    spec = yaml.safe_load(yaml_path.read_text())
    value = lambda v: float(eval(str(v), {"__builtins__": {}}, {"pi": math.pi}))  # noqa: E731  ("pi/2")

    def rot(axis, t):
        c, s_ = np.cos(t), np.sin(t)
        m = np.tile(np.eye(4), (len(t), 1, 1))
        i, j = {"x": (1, 2), "z": (0, 1)}[axis]
        m[:, i, i], m[:, i, j], m[:, j, i], m[:, j, j] = c, -s_, s_, c
        return m

    def trans(axis, d):
        m = np.eye(4)
        m["xyz".index(axis), 3] = d
        return m

    out = np.tile(np.eye(4), (len(q), 1, 1))
    for i, row in enumerate(spec["dh"]):
        a, alpha, d, theta = (value(row[k]) for k in ("a", "alpha", "d", "theta"))
        t = q[:, i] + theta
        if spec["convention"] == "standard":
            step = rot("z", t) @ trans("z", d) @ trans("x", a) @ rot("x", np.full(len(q), alpha))
        else:
            step = rot("x", np.full(len(q), alpha)) @ trans("x", a) @ rot("z", t) @ trans("z", d)
        out = out @ step
    return out


def _pinocchio_fk(urdf: Path, frame: str, q: np.ndarray) -> np.ndarray:
    pin = pytest.importorskip("pinocchio")
    model = pin.buildModelFromUrdf(str(urdf))
    data, fid = model.createData(), model.getFrameId(frame)
    out = []
    for qi in q:
        pin.framesForwardKinematics(model, data, qi)
        out.append(data.oMf[fid].homogeneous.copy())
    return np.stack(out)


def _mujoco_fk(xml: Path, bodies: list[str], q: np.ndarray) -> np.ndarray:
    mujoco = pytest.importorskip("mujoco")
    from tests.mjcf_util import compile_with_stand_in_assets  # the XML untouched, meshes served from memory

    model = compile_with_stand_in_assets(xml)
    data = mujoco.MjData(model)
    out = np.tile(np.eye(4), (len(q), len(bodies), 1, 1))
    for n, qi in enumerate(q):
        data.qpos[:] = 0
        data.qpos[: q.shape[-1]] = qi  # the chain's joints come first in the file (joint1..7, finger_joint1)
        mujoco.mj_kinematics(model, data)
        for k, body in enumerate(bodies):
            out[n, k, :3, :3] = data.body(body).xmat.reshape(3, 3)
            out[n, k, :3, 3] = data.body(body).xpos
    return out


REFERENCES = {
    "name": lambda q: _dh_table_fk(PANDA_YAML, q),  # the built-in "panda" is panda.yaml
    "yaml": lambda q: _dh_table_fk(YAML, q),
    "urdf": lambda q: _pinocchio_fk(FR3, "fr3_link8", q),
    "mjcf": lambda q: _mujoco_fk(PANDA_XML, ["hand", "left_finger"], q),
}


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_every_source_kind(dtype):
    """Each source kind through load_chain gives the dtype asked for and the FK of a reference that reads
    the source another way: the DH YAML by PyYAML and the products written out above, the URDF by Pinocchio,
    the MJCF by MuJoCo (the file compiled untouched). (Comparing with from_urdf & co. would compare
    load_chain with itself: it calls them.)"""
    tol = {"atol": 1e-5, "rtol": 0} if dtype == torch.float32 else {"atol": 1e-10, "rtol": 0}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # panda.xml's finger equality constraint is reported, not enforced
        chains = {
            "name": models.load_chain("panda", dtype=dtype),
            "yaml": models.load_chain(YAML, dtype=dtype),
            "urdf": models.load_chain(str(FR3), "fr3_link8", dtype=dtype),
            "mjcf": models.load_chain(PANDA_XML, ["hand", "left_finger"], dtype=dtype),
        }
    for kind, chain in chains.items():
        assert isinstance(chain, KinematicChain) and chain.dtype == dtype, kind
        q = _q(chain)
        with torch.no_grad():
            got = chain.forward_kinematics(q)
        assert got.dtype == dtype, kind
        want = torch.from_numpy(REFERENCES[kind](q.double().numpy()))
        torch.testing.assert_close(got.double(), want, **tol, msg=lambda m, k=kind: f"{k}: {m}")
    # the published figure (panda.yaml): at q = 0 the flange is at (0.088, 0, 0.926) m
    with torch.no_grad():
        home = chains["name"].forward_kinematics(torch.zeros(7, dtype=dtype))
    torch.testing.assert_close(home[:3, 3], torch.tensor([0.088, 0.0, 0.926], dtype=dtype), **tol)


def test_a_chain_is_copied_and_converted():
    chain = models.load("panda", dtype=torch.float64)
    same = models.load_chain(chain)
    assert same is not chain and same.dtype == torch.float64
    with torch.no_grad():
        same.d.add_(0.1)
    assert not torch.equal(same.d, chain.d)  # an independent copy
    as32 = models.load_chain(chain, dtype=torch.float32)
    assert as32.dtype == torch.float32 and chain.dtype == torch.float64


def test_errors_name_the_source():
    with pytest.raises(ModelError, match="fr3.urdf: a URDF or MJCF robot needs its end link"):
        models.load_chain(FR3)
    with pytest.raises(ModelError, match="panda.xml: a URDF or MJCF robot needs its end link"):
        models.load_chain(str(PANDA_XML))
    with pytest.raises(ModelError, match="applies to URDF and MuJoCo robots"):
        models.load_chain("panda", "hand")
    with pytest.raises(ModelError, match="unknown model 'nope'"):
        models.load_chain("nope")
    with pytest.raises(ModelError, match="got int"):
        models.load_chain(3)
    with pytest.raises(DeviceError):
        models.load_chain("panda", device="meta")


def test_the_callers_use_it(monkeypatch):
    """The CLI, calibrate_from_files and the envs load through models.load_chain."""
    import diffkin.calibration.io as cio
    from diffkin import cli
    from diffkin.cli import _common as cli_common

    calls = []
    real = models.load_chain

    def spy(*args, **kwargs):
        calls.append(args[0])
        return real(*args, **kwargs)

    monkeypatch.setattr(models, "load_chain", spy)
    monkeypatch.setattr("diffkin.models.loading.load_chain", spy, raising=False)
    args = cli.build_parser().parse_args(["fk", "--robot", "ur5", "--random", "2"])
    assert cli_common._load_chain(args).name == "ur5"
    with pytest.raises(Exception):  # noqa: B017  (no measurement file: only the loading matters here)
        cio.calibrate_from_files("three_link_planar", "missing.npz")
    from diffkin.envs.robot import load_chain as env_load

    assert env_load("panda").dtype == torch.float32
    assert calls == ["ur5", "three_link_planar", "panda"]

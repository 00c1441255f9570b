"""diffkin.models.load_chain, the one loader (CLI, calibrate_from_files, envs): every source kind gives the
chain the format's own builder gives (same FK), in the dtype and device asked for; errors name the source."""

from __future__ import annotations

import warnings
from pathlib import Path

import pytest
import torch

from diffkin import models
from diffkin.errors import DeviceError, ModelError

DATA = Path(__file__).parent / "data"
FR3 = DATA / "urdf" / "fr3.urdf"
PANDA_XML = DATA / "mjcf" / "franka_emika_panda" / "panda.xml"
YAML = Path(models.__file__).parent / "data" / "ur5.yaml"


def _same_fk(a, b):
    q = b.random_configuration(5, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        torch.testing.assert_close(a.forward_kinematics(q), b.forward_kinematics(q), atol=0, rtol=0)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_every_source_kind(dtype):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cases = [
            (models.load_chain("panda", dtype=dtype), models.load("panda", dtype=dtype)),
            (models.load_chain(YAML, dtype=dtype), models.load(YAML, dtype=dtype)),
            (models.load_chain(str(FR3), "fr3_link8", dtype=dtype),
             models.from_urdf(FR3, "fr3_link8", dtype=dtype)),
            (models.load_chain(PANDA_XML, ["hand", "left_finger"], dtype=dtype),
             models.from_mjcf(PANDA_XML, ["hand", "left_finger"], dtype=dtype)),
        ]
    for got, want in cases:
        assert type(got) is type(want) and got.dtype == dtype
        _same_fk(got, want)


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

    calls = []
    real = models.load_chain

    def spy(*args, **kwargs):
        calls.append(args[0])
        return real(*args, **kwargs)

    monkeypatch.setattr(models, "load_chain", spy)
    monkeypatch.setattr("diffkin.models.loading.load_chain", spy, raising=False)
    args = cli.build_parser().parse_args(["fk", "--robot", "ur5", "--random", "2"])
    assert cli._load_chain(args).name == "ur5"
    with pytest.raises(Exception):  # noqa: B017  (no measurement file: only the loading matters here)
        cio.calibrate_from_files("three_link_planar", "missing.npz")
    from diffkin.envs.robot import load_chain as env_load

    assert env_load("panda").dtype == torch.float32
    assert calls == ["ur5", "three_link_planar", "panda"]

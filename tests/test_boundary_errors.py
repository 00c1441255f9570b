"""Issue 30 item 10: each input the fuzz sweep and the newcomer found raising a raw exception (or giving NaN)
is refused once at the public boundary with one of the typed errors of ``diffkin.errors``, naming what was
expected and what came."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import torch

from diffkin import errors, ik, models
from diffkin.chain import DHChain
from diffkin.manipulability import condition_number, force_ellipsoid
from diffkin.redundancy import damped_pinv

F64 = torch.float64
ROOT = Path(__file__).resolve().parents[1]


def test_damped_pinv_refuses_a_damping_of_the_wrong_shape():
    J = torch.randn(4, 6, 7, dtype=F64)
    for k in (torch.ones(3, dtype=F64), torch.ones(4, 2, dtype=F64)):
        with pytest.raises(errors.ShapeError, match=r"damping.*\(4\)"):
            damped_pinv(J, k)
    assert damped_pinv(J, torch.full((4,), 0.1, dtype=F64)).shape == (4, 7, 6)  # per-batch damping is fine


def test_condition_number_and_force_ellipsoid_are_never_nan():
    J = torch.zeros(3, 6, dtype=F64)  # a (..., 6) input: one zero 3 x 6 matrix, singular
    assert float(condition_number(J)) == float("inf")
    tall = torch.randn(8, 6, dtype=F64)  # m > n: two directions without force transmission
    lengths = force_ellipsoid(tall).lengths
    assert not bool(lengths.isnan().any()) and bool(torch.isinf(lengths[-2:]).all())
    with pytest.raises(errors.ShapeError, match=r"\(0, 6\)"):
        condition_number(torch.zeros(0, 6, dtype=F64))  # no rows: no singular values
    with pytest.raises(errors.ShapeError, match=r"\(2, 0, 6\)"):
        force_ellipsoid(torch.zeros(2, 0, 6, dtype=F64))


def _poses(S: int) -> torch.Tensor:
    chain = models.load("panda", dtype=F64)
    q = chain.random_configuration((S,), generator=torch.Generator().manual_seed(0))
    return chain, q, chain.forward_kinematics(q).detach()


def test_one_sample_trajectories_keep_their_sample():
    chain, q, T = _poses(1)
    tw = ik.finite_difference_twists(T, 0.1)  # the last sample is at rest: one zero twist, not none
    assert tw.shape == (1, 6) and bool((tw == 0).all())
    assert ik.finite_difference_twists(T[..., :3, 3], 0.1).shape == (1, 3)
    assert ik.refine_path(T, 3).shape == (1, 4, 4)
    res = ik.joint_trajectory_from_poses(chain, T, q[0])
    torch.testing.assert_close(res.q[..., -1, :], q[0])


def test_models_load_refuses_a_non_utf8_yaml(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_bytes(b"name: x\n\xff\xfe: 1\n")
    with pytest.raises(errors.ModelError, match=r"bad\.yaml.*UTF-8"):
        models.load(str(path))


@pytest.mark.parametrize("device", ["meta", "cuda:99", "nonsense"])
def test_models_load_refuses_an_unusable_device(device):
    with pytest.raises(errors.DeviceError, match=repr(device).strip("'").split(":")[0]):
        models.load("ur5", device=device)


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks a CPU-only torch")
def test_models_load_refuses_cuda_on_a_cpu_only_torch():
    with pytest.raises(errors.DeviceError, match="cuda"):
        models.load("ur5", device="cuda")


def test_vector_env_refuses_an_unusable_device_and_a_missing_action():
    from diffkin.envs.vector import TorchVectorEnv

    bad = "meta" if torch.cuda.is_available() else "cuda"
    with pytest.raises(errors.DeviceError, match=bad):
        TorchVectorEnv("diffkin/Reach-v0", 2, device=bad)
    env = TorchVectorEnv("diffkin/Reach-v0", 2)
    env.reset(seed=0)
    with pytest.raises(errors.DTypeError, match="None"):
        env.step(None)


def test_train_with_a_malformed_config_is_a_clean_error(tmp_path):
    cfg = tmp_path / "bad.yaml"
    cfg.write_text("a: [1, 2\nb: : :\n")
    r = subprocess.run([sys.executable, "-m", "diffkin.cli", "train", "--config", str(cfg)], cwd=ROOT,
                       capture_output=True, text=True)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "internal" not in lines[0]
    assert "bad.yaml" in lines[0] and "YAML" in lines[0]


@pytest.mark.parametrize("limits", [[[-1e39, 1e39], [-1.0, 1.0]], torch.tensor([[-1.0, 1e39], [-1.0, 1.0]],
                                                                               dtype=F64)])
def test_q_limits_that_do_not_fit_float32_are_refused(limits):
    z = torch.zeros(2)
    with pytest.raises(errors.ModelError, match=r"q_limits.*float32"):
        DHChain(z, z, z, z, q_limits=limits, dtype=torch.float32)
    inf = DHChain(z, z, z, z, q_limits=[[-float("inf"), float("inf")], [-1, 1]], dtype=torch.float32)
    assert bool(torch.isinf(inf.q_limits[0]).all())  # ±inf (no limit) stays allowed
    assert DHChain(z, z, z, z, q_limits=limits, dtype=F64).q_limits.dtype == F64  # fits float64


def test_num_seeds_zero_raises_a_documented_subclass():
    chain = models.load("ur5", dtype=F64)
    T = chain.forward_kinematics(chain.random_configuration((2,))).detach()
    with pytest.raises(errors.OptionError, match=r"num_seeds.*>= 1.*0"):
        ik.solve(chain, T, num_seeds=0)
    assert issubclass(errors.OptionError, errors.DiffkinError)


def test_urdf_errors_name_their_file(tmp_path):
    path = tmp_path / "broken.urdf"
    path.write_text('<robot name="r"><link name="a"/><joint name="j" type="revolute"><parent link="a"/>'
                    '<child link="zz"/></joint></robot>')
    with pytest.raises(errors.ModelError) as info:
        models.from_urdf(path, "zz")
    assert str(info.value).startswith(str(path)), str(info.value)
    bad_xml = tmp_path / "bad_xml.urdf"
    bad_xml.write_text("<robot><link></robot>")
    with pytest.raises(errors.ModelError) as info:
        models.from_urdf(bad_xml, "a")
    assert str(info.value).startswith(str(bad_xml)), str(info.value)


def test_tensor_option_bounds_raise_one_error_type():
    """check_positive / check_nonnegative: OptionError naming the option and the bound; NaN left to
    check_finite unless ``nan=False`` (then NonFiniteOptionError, an OptionError); the public functions that
    route through them raise the same."""
    from diffkin.validation import check_nonnegative, check_positive

    x = torch.tensor([0.5, 0.0, 2.0], dtype=torch.float64)
    assert check_nonnegative(x, "w") is x
    with pytest.raises(errors.OptionError, match=r"expected damping > 0, got 1 non-positive"):
        check_positive(x, "damping")
    with pytest.raises(errors.OptionError, match=r"expected w >= 0, got 2 negative value\(s\) \(smallest -3"):
        check_nonnegative(torch.tensor([-1.0, 2.0, -3.0]), "w")
    nan = torch.tensor([1.0, float("nan")])
    assert check_nonnegative(nan, "limit") is nan
    with pytest.raises(errors.NonFiniteOptionError, match="limit >= 0, got 1 NaN"):
        check_nonnegative(nan, "limit", nan=False)
    chain = DHChain([0.3, 0.2], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0], dtype=torch.float64)
    q = torch.zeros(2, dtype=torch.float64)
    with pytest.raises(errors.OptionError, match="damping"):
        ik.velocity_step(chain, q, torch.zeros(6, dtype=torch.float64), 0.01, damping=0.0)
    with pytest.raises(errors.OptionError, match="velocity_limit"):
        ik.velocity_step(chain, q, torch.zeros(6, dtype=torch.float64), 0.01, velocity_limit=-1.0)

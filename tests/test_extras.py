"""Optional dependencies: the core runs without them, and each optional feature, when its package is
missing, fails with one MissingExtraError naming the extra (checked in subprocesses where the package is
made unimportable)."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

OPTIONAL = ["rich", "matplotlib", "gymnasium", "stable_baselines3", "tensorboard", "optuna", "viser", "scipy",
            "pytorch_kinematics", "mkdocs"]


def _run(code: str, hide: list[str]) -> subprocess.CompletedProcess:
    prelude = f"import sys\nfor _m in {hide!r}:\n    sys.modules[_m] = None  # import raises ImportError\n"
    return subprocess.run([sys.executable, "-c", prelude + textwrap.dedent(code)], capture_output=True,
                          text=True)


def test_the_core_needs_no_optional_package(tmp_path):
    out = _run(f"""
        import torch
        from diffkin import ik, models
        from diffkin.cli import main
        from importlib.resources import files
        chain = models.load("panda", dtype=torch.float64)
        q = chain.random_configuration(50, generator=torch.Generator().manual_seed(0))
        res = ik.solve(chain, chain.forward_kinematics(q))
        assert bool(res.success.all())
        ur5 = models.from_urdf(str(files("diffkin.models") / "data" / "ur5.urdf"), "tool0")
        assert ur5.n_joints == 6
        assert main(["fk", "--robot", "panda", "--random", "100", "--output", r"{tmp_path / 'T.npy'}"]) == 0
        assert main(["ik", "--robot", "panda", "--random", "20"]) == 0
        assert not any(m in sys.modules and sys.modules[m] is not None for m in {OPTIONAL!r})
        """, OPTIONAL)
    assert out.returncode == 0, out.stderr[-3000:]
    assert "successes" in out.stdout  # the IK summary as a plain-text table


@pytest.mark.parametrize(("code", "hide", "extra"), [
    ("import diffkin.envs", ["gymnasium"], "gym"),
    ("import diffkin.training.train", ["stable_baselines3"], "rl"),
    ("from diffkin.training.algos import algo_class; algo_class('tqc')", ["sb3_contrib"], "contrib"),
    ("from diffkin.training.algos import import_env_package; import_env_package('PandaReach-v3')",
     ["panda_gym"], "panda"),
    ("""
     import torch
     from diffkin import calibration, models
     chain = models.load("three_link_planar", dtype=torch.float64)
     q = chain.random_configuration(20, generator=torch.Generator().manual_seed(0))
     res = calibration.calibrate(chain, q, chain.forward_kinematics(q).detach())
     res.plot_residuals("r.png")
     """, ["matplotlib"], "plot"),
])
def test_a_missing_extra_is_named(code, hide, extra, tmp_path):
    out = _run(f"import os\nos.chdir({str(tmp_path)!r})\n" + textwrap.dedent(code), hide)
    assert out.returncode != 0
    last = out.stderr.strip().splitlines()[-1]
    assert "MissingExtraError" in last and f"pip install 'diffkin[{extra}]'" in last, out.stderr[-2000:]


def test_the_command_names_the_extra_in_one_line(tmp_path):
    out = _run(f"""
        from diffkin.cli import main
        raise SystemExit(main(["trajectory", "joint", "--start", "0", "--end", "1",
                               "--output", r"{tmp_path / 't.csv'}", "--plot", r"{tmp_path / 't.png'}"]))
        """, ["matplotlib"])
    assert out.returncode == 2
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:") and "diffkin[plot]" in lines[0], out.stderr

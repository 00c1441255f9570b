"""The public API: every exported name exists, and the library never imports the RL code."""

import importlib
import subprocess
import sys

import pytest

import diffkin

MODULES = [
    "diffkin",
    "diffkin.rotations",
    "diffkin.transforms",
    "diffkin.models",
    "diffkin.jacobian",
    "diffkin.ik",
    "diffkin.calibration",
    "diffkin.trajectories",
    "diffkin.collision",
]


@pytest.mark.parametrize("module_name", MODULES)
def test_every_exported_name_exists(module_name):
    module = importlib.import_module(module_name)
    assert module.__all__, f"{module_name} has an empty __all__"
    missing = [name for name in module.__all__ if not hasattr(module, name)]
    assert not missing, f"{module_name}.__all__ names missing attributes: {missing}"


def test_contract_names_from_the_issues():
    from diffkin import calibration, ik, jacobian, models, rotations, trajectories, transforms

    for mod, names in {
        rotations: [
            "rot_x",
            "rot_y",
            "rot_z",
            "skew",
            "euler_to_matrix",
            "matrix_to_euler",
            "euler_rate_matrix",
            "axis_angle_to_matrix",
            "matrix_to_axis_angle",
            "quaternion_to_matrix",
            "matrix_to_quaternion",
            "quaternion_multiply",
            "quaternion_conjugate",
            "quaternion_slerp",
        ],
        transforms: ["transform_inverse", "compose", "transform_points", "pose_error"],
        models: ["load", "available", "from_urdf"],
        jacobian: ["geometric_jacobian", "analytical_jacobian", "forward_kinematics_and_jacobian"],
        ik: ["closed_form", "solve", "optimize", "clik"],
        calibration: ["calibrate"],
        trajectories: ["cubic", "quintic", "trapezoidal", "cubic_spline"],
    }.items():
        missing = [n for n in names if not callable(getattr(mod, n, None))]
        assert not missing, f"{mod.__name__} lacks {missing}"
    assert set(models.available()) >= {
        "three_link_planar",
        "parallelogram",
        "spherical_arm",
        "anthropomorphic_arm",
        "spherical_wrist",
        "stanford",
        "anthropomorphic_wrist",
        "dlr",
        "humanoid_arm",
        "panda",
        "ur5",
        "kuka_iiwa14",
    }


def test_dh_parameters_are_named_parameters():
    chain = diffkin.models.load("panda")
    names = {"a", "alpha", "d", "theta", "base_delta", "tool_delta"}  # the DH table, learnable base and tool
    assert {name for name, _ in chain.named_parameters()} == names


def test_library_does_not_import_rl_code():
    code = (
        "import sys, diffkin, diffkin.cli, diffkin.demo; "
        "bad = [m for m in sys.modules if m.split('.')[0] in ('envs', 'training', 'configs', 'gymnasium', "
        "'stable_baselines3')]; print(bad); sys.exit(1 if bad else 0)"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout + proc.stderr

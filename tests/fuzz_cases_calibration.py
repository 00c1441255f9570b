"""Fuzz cases of calibration and the environments
(see ``tests/fuzzing.py`` for the format).

Calibration functions follow their chain's dtype: each wrapper takes the chain (or model) of the dtype of its
first argument, so a float32 call uses a float32 chain and the ``mixed`` mutation of any argument mixes.
The environments compute in their own dtype (float32 by default) and take actions as Gymnasium does: numpy
arrays (the normal case) or float32/float64 tensors, cast to the env's dtype — so their single-argument
cases have no ``mixed`` mutation.
"""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path

import numpy as np
import torch

from diffkin.chain import DHChain
from diffkin.errors import ShapeError
from tests.fuzzing import Arg, Case, transform, uniform

#: modules whose every public callable must have a case or an exemption
MODULES: list[str] = [
    "diffkin.calibration",
    "diffkin.envs.core",
    "diffkin.envs.reach",
    "diffkin.envs.track",
    "diffkin.envs.vector",
    "diffkin.envs.robot",
    "diffkin.training.evaluate",
    "diffkin.training.sb3",
]

# ----------------------------------------------------------------------------------------- calibration
N_JOINTS, N_POSES = 3, 4
_CHAINS: dict[torch.dtype, DHChain] = {}


def _dtype_of(x) -> torch.dtype:
    """The float dtype a call's first argument asks for (float64 for anything else: the call must refuse)."""
    dt = getattr(x, "dtype", None)
    if dt in (torch.float32, np.float32):
        return torch.float32
    return torch.float64


def _chain(x) -> DHChain:
    """A small spatial 3R arm (no parallel axes: the plain DH error model) of ``x``'s dtype, cached."""
    dtype = _dtype_of(x)
    if dtype not in _CHAINS:
        _CHAINS[dtype] = DHChain(
            [0.1, 0.3, 0.2], [math.pi / 2, -math.pi / 2, 0.4], [0.3, 0.05, 0.1], [0.0, 0.0, 0.0],
            q_limits=[(-math.pi, math.pi)] * 3, name="fuzz3r", dtype=dtype,
        )
    return _CHAINS[dtype]


def _model(x):
    from diffkin.calibration import CalibrationModel

    return CalibrationModel.from_chains(_chain(x))


def _params(gen, batch, dtype):
    """ζ near the fuzz chain's nominal (P = 4n + 12)."""
    nominal = _model(torch.empty(0, dtype=dtype)).nominal.to(dtype)
    return nominal + 1e-3 * torch.randn(*batch, nominal.shape[-1], generator=gen, dtype=dtype)


def _poses(gen, batch, dtype):
    """Measured poses ``(*batch, N, 4, 4)``."""
    return transform(gen, (*batch, N_POSES), dtype)


def _calibrate(q, T):
    from diffkin.calibration import calibrate

    return calibrate(_chain(q), q, T, max_iterations=2, cross_validation=0, progress=False)


def _calibrate_batch(q, T):
    from diffkin.calibration import calibrate_batch

    return calibrate_batch(_chain(q), q, T, "least_squares", max_iterations=2, progress=False)


def _robots_by_poses(results) -> torch.Tensor:
    """A stand-in of shape (K, N) for the batch-dims check of a list of K results over N poses."""
    return torch.empty(len(results), results[0].q.shape[0] if results else N_POSES)


def _calibration_loss(params, q, T):
    from diffkin.calibration import calibration_loss

    return calibration_loss(params, q, T, _model(params))


def _validation_error(q, T):
    from diffkin.calibration import validation_error

    out = validation_error(_chain(q), q, T)
    return torch.tensor([v for v in out.values() if v is not None], dtype=torch.float64)


def _identifiability(q, T):
    from diffkin.calibration import identifiability

    rep = identifiability(_chain(q), q, T)
    return torch.tensor([rep.rank, rep.condition_number, rep.o1, rep.o3, *rep.singular_values],
                        dtype=torch.float64)


def _select_poses(candidates):
    from diffkin.calibration import select_poses

    return select_poses(_chain(candidates), candidates, 2).to(torch.float64)


def _robust_loss(sq_norm):
    from diffkin.calibration import robust_loss

    return robust_loss(sq_norm, "soft_l1", 1e-3)


def _q(gen, batch, dtype):
    return uniform(N_JOINTS, low=-2.0, high=2.0)(gen, batch, dtype)


def _q_poses(gen, batch, dtype):
    return uniform(N_POSES, N_JOINTS, low=-2.0, high=2.0)(gen, batch, dtype)


# ------------------------------------------------------------------------------------------ environments
_ENVS: dict[str, object] = {}
ENV_ROBOT, N_ENVS = "three_link_planar", 3


def _env(kind: str):
    if kind not in _ENVS:
        from diffkin.envs.reach import ReachEnv
        from diffkin.envs.track import TrackEnv
        from diffkin.envs.vector import TorchVectorEnv
        from diffkin.training.sb3 import SB3VecEnv

        make = {
            "reach": lambda: ReachEnv(ENV_ROBOT, reward_type="dense"),
            "track": lambda: TrackEnv(ENV_ROBOT, episode_steps=5),
            "vector": lambda: TorchVectorEnv("diffkin/Reach-v0", N_ENVS, robot=ENV_ROBOT,
                                             reward_type="dense"),
            "sb3": lambda: SB3VecEnv(TorchVectorEnv("diffkin/Track-v0", N_ENVS, robot=ENV_ROBOT,
                                                    episode_steps=5)),
            # on the manifold: a ball shoulder (nq 8, nv 7), joint velocities observed
            "reach_ball": lambda: ReachEnv(_ball_arm(), reward_type="dense", observation=(
                "ee_position", "joint_positions", "joint_velocities")),
            # self-collision checked: the fold arm's spheres (tests/data/envs)
            "reach_collision": lambda: ReachEnv(_fold_arm(), self_collision="penalize", reward_type="dense"),
        }
        _ENVS[kind] = make[kind]()
    return _ENVS[kind]


_DATA = Path(__file__).parent / "data"


def _ball_arm():
    from diffkin.models import from_mjcf

    return from_mjcf(_DATA / "mjcf_extra" / "joint_kinds.xml", "palm", root_link="torso")


def _fold_arm():
    from diffkin.models import from_urdf

    return from_urdf(_DATA / "envs" / "fold_arm.urdf", "tool")


def _as_tensors(*items) -> list[torch.Tensor]:
    """Env outputs (numpy, floats, bools, dicts) as float64 tensors, for the harness's comparisons."""
    out = []
    for x in items:
        if isinstance(x, dict):
            out += _as_tensors(*(x[k] for k in sorted(x)))
        elif isinstance(x, list):
            out += _as_tensors(*x)
        elif isinstance(x, torch.Tensor):
            out.append(x.detach().to(torch.float64))
        else:
            out.append(torch.as_tensor(np.asarray(x, dtype=np.float64)))
    return out


def _single_step(kind: str):
    def step(action):
        env = _env(kind)
        env.reset(seed=0)
        obs, reward, terminated, truncated, info = env.step(action)
        return _as_tensors(obs, reward, terminated, truncated, info)

    return step


def _vector_step(actions):
    venv = _env("vector")
    venv.reset(seed=0)
    return _as_tensors(*venv.step(actions)[:4])


def _sb3_step(actions):
    venv = _env("sb3")
    venv.seed(0)
    venv.reset()
    obs, reward, done, _ = venv.step(actions)
    return _as_tensors(obs, reward, done)


def _reach_reward(achieved, desired):
    from diffkin.envs.reach import reach_reward

    return torch.as_tensor(np.asarray(reach_reward(achieved, desired, "dense", 0.05))).to(torch.float64)


def _check_action(action):
    from diffkin.envs.core import check_action

    return torch.as_tensor(check_action(action, (N_JOINTS,)), dtype=torch.float64)


def _joint_action(gen, batch, dtype):
    return uniform(N_JOINTS)(gen, batch, dtype)


def _cases() -> list[Case]:
    from diffkin import calibration as cal
    from diffkin.envs import core, reach, track, vector
    from diffkin.training import sb3

    no_batch = None  # results without the call's batch dims (a report, a dict of numbers, an env step)
    return [
        Case("calibration.calibrate", _calibrate, covers=cal.calibrate,
             args={"q": _arg(_q, (N_JOINTS,)), "T": _arg(transform, (4, 4))},
             batch=(N_POSES,), out_batch=lambda r: r.q, empty_raises=ShapeError),
        Case("calibration.calibrate_batch", _calibrate_batch, covers=cal.calibrate_batch,
             args={"q": _arg(_q, (N_JOINTS,)), "T": _arg(transform, (4, 4))},
             batch=(2, N_POSES), out_batch=_robots_by_poses),
        Case("calibration.calibration_loss", _calibration_loss, covers=cal.calibration_loss,
             args={"params": _arg(_params, (4 * N_JOINTS + 12,)), "q": _arg(_q_poses, (N_POSES, N_JOINTS)),
                   "T": _arg(_poses, (N_POSES, 4, 4))}),
        Case("calibration.robust_loss", _robust_loss, covers=cal.robust_loss,
             args={"sq_norm": _arg(uniform(5, low=0.0, high=1e-5), None)}),
        Case("calibration.validation_error", _validation_error, covers=cal.validation_error,
             args={"q": _arg(_q, (N_JOINTS,)), "T": _arg(transform, (4, 4))},
             batch=(N_POSES,), out_batch=no_batch, empty_raises=ShapeError),
        Case("calibration.identifiability", _identifiability, covers=cal.identifiability,
             args={"q": _arg(_q, (N_JOINTS,)), "T": _arg(transform, (4, 4))},
             batch=(N_POSES,), out_batch=no_batch, empty_raises=ShapeError, rtol=1e-4),
        # select 2 of M candidates: an empty candidate set has nothing to select from
        Case("calibration.select_poses", _select_poses, covers=cal.select_poses,
             args={"candidates": _arg(_q, (N_JOINTS,))}, batch=(6,), out_batch=no_batch,
             empty_raises=ShapeError),
        # envs: one action per step (not batched: the empty mutation leaves it valid)
        Case("diffkin.envs.ReachEnv.step", _single_step("reach"), covers=reach.ReachEnv,
             args={"action": _arg(_joint_action, (N_JOINTS,), batched=False)}, out_batch=no_batch,
             rtol=1e-5),
        Case("diffkin.envs.TrackEnv.step", _single_step("track"), covers=track.TrackEnv,
             args={"action": _arg(_joint_action, (N_JOINTS,), batched=False)}, out_batch=no_batch,
             rtol=1e-5),
        Case("diffkin.envs.ReachEnv.step[self_collision]", _single_step("reach_collision"),
             covers=reach.ReachEnv, args={"action": _arg(_joint_action, (N_JOINTS,), batched=False)},
             out_batch=no_batch, rtol=1e-5),
        *([Case("diffkin.envs.ReachEnv.step[ball joint]", _single_step("reach_ball"), covers=reach.ReachEnv,
                args={"action": _arg(uniform(7), (7,), batched=False)}, out_batch=no_batch, rtol=1e-5)]
          if importlib.util.find_spec("mujoco") else []),
        Case("diffkin.envs.check_action", _check_action, covers=core.check_action,
             args={"action": _arg(_joint_action, (N_JOINTS,), batched=False)}, out_batch=no_batch),
        # the vector envs' env count is fixed at construction: 0 actions for 3 envs is a wrong shape
        Case("diffkin.envs.TorchVectorEnv.step", _vector_step, covers=vector.TorchVectorEnv,
             args={"actions": _arg(_joint_action, (N_JOINTS,))}, batch=(N_ENVS,), out_batch=no_batch,
             empty_raises=ShapeError, rtol=1e-5),
        Case("diffkin.training.SB3VecEnv.step", _sb3_step, covers=sb3.SB3VecEnv,
             args={"actions": _arg(_joint_action, (N_JOINTS,))}, batch=(N_ENVS,), out_batch=no_batch,
             empty_raises=ShapeError, rtol=1e-5),
        Case("diffkin.envs.reach_reward", _reach_reward, covers=reach.reach_reward,
             args={"achieved_goal": _arg(uniform(3), (3,)), "desired_goal": _arg(uniform(3), (3,))},
             rtol=1e-5),
    ]


def _arg(make, trailing, batched: bool = True, finite: bool = True) -> Arg:
    return Arg(make, trailing, batched, finite)


CASES: list[Case] = _cases()

_TRUSTED = "batched task logic on trusted state tensors; user input enters through the env's step (fuzzed)"
#: public callables without a case, with the reason
_HAND_EYE = ("camera calibration on pose sets (rigid, >= 3 poses with two rotation axes): bad shapes, NaN, "
             "non-rigid and degenerate sets are unit-tested in tests/test_hand_eye.py::test_bad_inputs and "
             "::test_degenerate_motions_raise; no fuzz case yet")
EXEMPT: dict[str, str] = {
    "diffkin.calibration.hand_eye": _HAND_EYE,
    "diffkin.calibration.robot_world_hand_eye": _HAND_EYE,
    "diffkin.calibration.motion_axis_spread": _HAND_EYE,
    "diffkin.calibration.project_points": "pinhole projection: shapes checked in "
    "tests/test_camera_projection.py::test_bad_shapes; no fuzz case yet",
    "diffkin.calibration.CalibrationResult": "result container",
    "diffkin.calibration.CameraCalibrationResult": "result container",
    "diffkin.calibration.ContactCalibrationResult": "result container",
    "diffkin.calibration.calibrate_contacts": "a fit over touch-probe postures (seconds a call): readings "
    "of another robot, NaN, fixture indices of another shape or range, non-positive radii, too few contacts "
    "and degenerate tips are unit-tested in tests/test_calibrate_contacts.py::test_bad_inputs_are_refused; "
    "no fuzz case yet",
    "diffkin.calibration.calibrate_camera": "a fit over images (seconds a call): bad shapes (another board "
    "size, another robot), NaN at visible points, unknown options and degenerate postures are unit-tested in "
    "tests/test_calibrate_camera.py::test_bad_inputs_are_refused; no fuzz case yet",
    "diffkin.calibration.BoardDetection": "result container",
    "diffkin.calibration.detect_board": "reads images (OpenCV's detector): bad boards, options and files "
    "are unit-tested in tests/test_board_detection.py::test_bad_boards_and_inputs_are_refused; its tensors "
    "then go through calibrate_camera",
    "diffkin.calibration.IdentifiabilityReport": "result container",
    "diffkin.calibration.CalibrationModel": "the solvers' measurement model (built from chains; its methods "
                                            "take the trusted tensors of the hot path; user input enters "
                                            "through calibration_loss / calibrate, which validate)",
    "diffkin.calibration.ChainErrorModel": "the solvers' error model of a chain's own parameters (built from "
                                           "chains; trusted tensors on the hot path, as CalibrationModel)",
    "diffkin.calibration.calibrate_from_files": "reads files (the formats' checks are diffkin.io.data's); "
                                                "the arrays then go through calibrate (fuzzed)",
    "diffkin.calibration.load_measurements": "reads files (diffkin.io.data); no tensor input",
    "diffkin.calibration.parameter_names": "takes a joint count, no tensor input",
    "diffkin.envs.core.Task": "base class: " + _TRUSTED,
    "diffkin.envs.core.TaskEnv": "base class of ReachEnv / TrackEnv (fuzzed through them)",
    "diffkin.envs.core.to_numpy": "converts the env's own observation tensors, no user input",
    "diffkin.envs.reach.ReachTask": _TRUSTED,
    "diffkin.envs.reach.ReachConfig": "settings of Python numbers, checked on construction (test_envs)",
    "diffkin.envs.track.TrackTask": _TRUSTED,
    "diffkin.envs.track.TrackConfig": "settings of Python numbers, checked on construction (test_envs)",
    "diffkin.envs.vector.make_task": "factory of a task from keyword settings, no tensor input",
    "diffkin.training.sb3.make_sb3_vec_env": "factory of an SB3VecEnv (fuzzed as training.SB3VecEnv.step)",
    "diffkin.envs.robot.Robot": "the robot half of the envs: trusted, already validated tensors (module doc)",
    "diffkin.envs.robot.RobotConfig": "settings of Python numbers, checked on construction (test_envs)",
    "diffkin.envs.robot.load_chain": "takes a model name or a chain, no tensor input",
    "diffkin.envs.robot.robot_collision": "takes a chain and a RobotCollision (type-checked), no tensor "
                                          "input; its distances enter through ReachEnv.step (fuzzed)",
    "diffkin.training.evaluate.run_episodes": "takes an env and a policy; the policy's actions go through "
                                      "TorchVectorEnv.step (fuzzed)",
    "diffkin.training.evaluate.scripted_policy": "reads the env's own state, no user input",
    "diffkin.training.evaluate.run_vec_episodes": "takes an SB3 VecEnv and model; the actions are the "
                                                  "model's and go through the env's own step",
    "diffkin.training.evaluate.model_policy": "wraps a trained SB3 model, no tensor input",
    "diffkin.training.evaluate.load_run": "reads a run directory",
    "diffkin.training.evaluate.evaluate_run": "reads a run directory",
    "diffkin.training.evaluate.evaluate_and_save": "reads and writes a run directory",
    "diffkin.training.evaluate.main": "command-line entry point (argument parsing)",
}

"""Kinematic calibration (textbook §2.11): identify DH-parameter errors from measured end-effector poses.

``calibrate(chain, q, T, method="least_squares" | "gradient")`` returns a :class:`CalibrationResult` with a
calibrated copy of the chain; ``calibrate_batch`` does K robots in one vectorised call;
``calibration_loss`` is the differentiable objective for bigger pipelines; ``identifiability`` and
``select_poses`` analyse and design the pose set; ``validation_error`` scores a chain on held-out poses.
``hand_eye`` and ``robot_world_hand_eye`` solve AX = XB / AX = ZB for cameras with OpenCV's conventions;
``calibrate_camera`` fits the robot's geometry with the camera's and a board's poses to board pixels;
``detect_board`` finds a chessboard's corners in images (OpenCV) in the order it expects;
``calibrate_contacts`` fits the robot's geometry to a probe tip touching fixed spheres or planes.

Calibration estimates its own parameter vector ζ (on a private copy of the chain), never the chain's
``requires_grad``: a frozen chain (the default of every loader) calibrates as a learnable one does, and the
calibrated chain is as learnable as the nominal one given, parameter by parameter.
"""

from .api import METHODS as METHODS
from .api import CalibrationResult as CalibrationResult
from .api import calibrate as calibrate
from .api import calibrate_batch as calibrate_batch
from .api import validation_error as validation_error
from .board import BoardDetection as BoardDetection
from .board import detect_board as detect_board
from .camera import project_points as project_points
from .camera_api import calibrate_camera as calibrate_camera
from .camera_result import CameraCalibrationResult as CameraCalibrationResult
from .contact_api import ContactCalibrationResult as ContactCalibrationResult
from .contact_api import calibrate_contacts as calibrate_contacts
from .error_models import ERROR_MODELS as ERROR_MODELS
from .error_models import ChainErrorModel as ChainErrorModel
from .handeye import HAND_EYE_METHODS as HAND_EYE_METHODS
from .handeye import ROBOT_WORLD_METHODS as ROBOT_WORLD_METHODS
from .handeye import DegenerateMotionError as DegenerateMotionError
from .handeye import hand_eye as hand_eye
from .handeye import motion_axis_spread as motion_axis_spread
from .handeye import robot_world_hand_eye as robot_world_hand_eye
from .identifiability import IdentifiabilityReport as IdentifiabilityReport
from .identifiability import identifiability as identifiability
from .identifiability import select_poses as select_poses
from .io import calibrate_from_files as calibrate_from_files
from .io import load_measurements as load_measurements
from .model import CalibrationModel as CalibrationModel
from .model import parameter_names as parameter_names
from .solvers import LOSSES as LOSSES
from .solvers import calibration_loss as calibration_loss
from .solvers import robust_loss as robust_loss

__all__ = [
    "METHODS",
    "ERROR_MODELS",
    "ChainErrorModel",
    "LOSSES",
    "HAND_EYE_METHODS",
    "ROBOT_WORLD_METHODS",
    "DegenerateMotionError",
    "CalibrationResult",
    "CameraCalibrationResult",
    "ContactCalibrationResult",
    "BoardDetection",
    "CalibrationModel",
    "IdentifiabilityReport",
    "calibrate",
    "calibrate_batch",
    "calibrate_camera",
    "calibrate_contacts",
    "calibrate_from_files",
    "detect_board",
    "calibration_loss",
    "hand_eye",
    "motion_axis_spread",
    "robot_world_hand_eye",
    "identifiability",
    "load_measurements",
    "parameter_names",
    "project_points",
    "robust_loss",
    "select_poses",
    "validation_error",
]

"""docs/img/camera_calibration_image_residuals.png: one rendered picture of the Panda eye-to-hand scene of
``tests/test_board_detection.py`` (``benchmarks/board_images.py``: the board drawn through the true camera
with OpenCV's lens distortion, blur and noise; the robot's geometry off by up to ±1 mm / ±0.1°) with the
detected corners, their projections by the nominal robot (the start) and by the calibrated one, and the
residuals magnified (``CameraCalibrationResult.plot_image_residuals``): what ``diffkin calibrate --images``
writes per picture into ``residuals/``. 20 full-size pictures, sector-based detector.
Run from the repository root: ``python docs/img/camera_calibration_image_residuals.py``."""

from __future__ import annotations

import warnings
from pathlib import Path

from benchmarks.board_images import COLS, ROWS, SQUARE, render, rendered_scene
from benchmarks.camera_scenes import DIST, K
from diffkin.calibration import calibrate_camera, detect_board

OUT = Path(__file__).resolve().parent / "camera_calibration_image_residuals.png"


def main() -> None:
    nominal, true, q, q_out, cam, board, T = rendered_scene(20)
    images = render(T)
    det = detect_board(images, (ROWS, COLS), SQUARE, detector="sb")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = calibrate_camera(nominal, q, det.image_points, det.board_points, camera_matrix=K,
                               dist_coeffs=DIST, visible=det.visible, measurement_noise=0.3,
                               cross_validation=0, progress=False)
    i = int(res.initial_image_rms.argmax())  # the picture the nominal robot gets most wrong
    print(res.summary().splitlines()[1], f"; picture {i}: {float(res.initial_image_rms[i]):.3f} -> "
          f"{float(res.image_rms[i]):.3f} px")
    res.plot_image_residuals(i, OUT, images[i], title=f"rendered picture {i} of {len(images)}: reprojection "
                             "before / after calibration")


if __name__ == "__main__":
    main()

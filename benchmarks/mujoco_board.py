"""A chessboard on the flange of MuJoCo Menagerie's Franka Panda, pictured by ``mujoco.Renderer`` (issue 38
step 3's end-to-end test with an independent renderer; ``tests/test_board_detection.py``).

The model is ``tests/data/mjcf/franka_emika_panda/panda.xml`` (XML only: its meshes become invisible
stand-ins, as diffkin's loader does), with a board added to the ``hand`` body by ``mujoco.MjSpec``: a white
plate and one thin black box per dark square (exact geometry, no texture mapping), lit by the headlight's
ambient term only (flat grey levels, no shading), and a fixed camera. The board frame is detect_board's (the
first inner corner at the origin, x along a row, y down the rows, the printed side facing −z); the
camera's intrinsics follow from its ``fovy`` and the image size: f = (H/2) / tan(fovy/2), and, OpenCV
counting pixel centres from 0 where OpenGL counts pixel edges, c = (W/2 − 0.5, H/2 − 0.5).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from .board_images import COLS, ROWS, SQUARE
from .camera_scenes import look_at

ROOT = Path(__file__).resolve().parents[1]
PANDA_XML = ROOT / "tests" / "data" / "mjcf" / "franka_emika_panda" / "panda.xml"
F64 = torch.float64
#: T_hand_board: the board's centre 12 cm out along the hand's z (past the fingers), its printed side facing
#: out (the board frame's z is the hand's -z)
BOARD_ON_HAND = torch.tensor([[1.0, 0, 0, -0.1], [0, -1, 0, 0.0625], [0, 0, -1, 0.12], [0, 0, 0, 1]],
                             dtype=F64)


CAMERA = look_at([1.3, 0.5, 0.9], [0.45, 0.0, 0.45])  # T_base_cam (OpenCV axes)


def build(width: int = 960, height: int = 768, fovy: float = 35.0):
    """``(mujoco.MjModel, camera_matrix K (3, 3))``: the Panda with the board and the camera ``CAMERA``."""
    import mujoco

    from diffkin.models.mjcf import _strip_assets

    spec = mujoco.MjSpec.from_file(str(PANDA_XML))
    _strip_assets(spec)
    for g in spec.geoms:  # the robot's own geoms (stand-ins once the meshes are gone): not pictured
        g.rgba = [0, 0, 0, 0]
    for light in list(spec.lights):
        spec.delete(light)
    spec.visual.headlight.ambient = [1.0, 1.0, 1.0]
    spec.visual.headlight.diffuse = [0.0, 0.0, 0.0]
    spec.visual.headlight.specular = [0.0, 0.0, 0.0]
    spec.visual.global_.offwidth, spec.visual.global_.offheight = width, height
    hand = spec.body("hand")
    R = BOARD_ON_HAND[:3, :3].numpy()
    t = BOARD_ON_HAND[:3, 3].numpy()

    def box(centre_board, half, rgba):
        p = R @ np.asarray(centre_board) + t
        quat = np.zeros(4)
        mujoco.mju_mat2Quat(quat, R.reshape(-1).copy())
        hand.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=half, pos=p, quat=quat, rgba=rgba,
                      contype=0, conaffinity=0, mass=0.0)

    cx, cy = (COLS - 1) * SQUARE / 2, (ROWS - 1) * SQUARE / 2
    # the plate: one square of white margin around the (ROWS + 1) x (COLS + 1) squares, 3 mm behind z = 0
    box([cx, cy, 0.0015], [(COLS + 3) * SQUARE / 2, (ROWS + 3) * SQUARE / 2, 0.0015], [0.9, 0.9, 0.9, 1])
    for a in range(COLS + 1):
        for b in range(ROWS + 1):
            if (a + b) % 2 == 0:  # square (a, b) spans x in [(a - 1) s, a s]: the first one dark
                box([(a - 0.5) * SQUARE, (b - 0.5) * SQUARE, -5e-5], [SQUARE / 2, SQUARE / 2, 5e-5],
                    [0.1, 0.1, 0.1, 1])
    R_mj = CAMERA[:3, :3].numpy() @ np.diag([1.0, -1.0, -1.0])  # MuJoCo's camera looks along its -z, y up
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, R_mj.reshape(-1).copy())
    spec.worldbody.add_camera(name="board_cam", pos=CAMERA[:3, 3].numpy(), quat=quat, fovy=fovy)
    model = spec.compile()
    f = (height / 2) / math.tan(math.radians(fovy) / 2)
    K = torch.tensor([[f, 0, width / 2 - 0.5], [0, f, height / 2 - 0.5], [0, 0, 1]], dtype=F64)
    return model, K


def render(model, q: torch.Tensor, width: int = 960, height: int = 768) -> list[np.ndarray]:
    """uint8 grey pictures ``(H, W)`` of the board camera at the arm's joint values ``q (N, 7)``."""
    import mujoco

    data = mujoco.MjData(model)
    out = []
    with mujoco.Renderer(model, height, width) as r:
        for qi in q.numpy():
            data.qpos[:7] = qi
            mujoco.mj_forward(model, data)
            r.update_scene(data, camera="board_cam")
            rgb = r.render()
            out.append(np.round(rgb.astype(np.float64).mean(-1)).astype(np.uint8))
    return out


def postures(chain, K: torch.Tensor, n: int, seed: int = 0, width: int = 960, height: int = 768):
    """``(q (n, 7), T_cam_board (n, 4, 4))``: random postures of ``chain`` (the Menagerie Panda to its hand)
    whose board faces the camera with every inner corner 30 px inside the picture."""
    from diffkin.calibration.board import board_points
    from diffkin.transforms import transform_inverse

    q = chain.random_configuration(4000, generator=torch.Generator().manual_seed(seed))
    with torch.no_grad():
        T = transform_inverse(CAMERA) @ chain.forward_kinematics(q) @ BOARD_ON_HAND
    pts = board_points(ROWS, COLS, SQUARE)
    p = (T[:, None, :3, :3] @ pts[None, :, :, None])[..., 0] + T[:, None, :3, 3]
    uv = p[..., :2] / p[..., 2:] * K[0, 0] + K[:2, 2]
    inside = (uv > 30).all(-1) & (uv[..., 0] < width - 30) & (uv[..., 1] < height - 30)
    ok = (T[:, 2, 2] > 0.5) & (p[..., 2] > 0.2).all(-1) & inside.all(-1)
    if int(ok.sum()) < n:
        raise ValueError(f"only {int(ok.sum())} postures show the whole board")
    return q[ok][:n], T[ok][:n]


def main(argv=None) -> None:
    """``python -m benchmarks.mujoco_board Q.npy OUT.npz [FOVY]``: the pictures at the joint values of Q.npy
    (N, 7) and the camera matrix, in OUT.npz (``images`` (N, H, W) uint8, ``K``); run in its own process so
    that MUJOCO_GL (egl for headless machines) is read before MuJoCo is imported."""
    import sys

    args = sys.argv[1:] if argv is None else argv
    model, K = build(fovy=float(args[2]) if len(args) > 2 else 35.0)
    q = torch.tensor(np.load(args[0]), dtype=F64)
    np.savez(args[1], images=np.stack(render(model, q)), K=K.numpy())


if __name__ == "__main__":
    main()

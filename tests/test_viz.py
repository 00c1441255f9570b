"""diffkin.viz / `diffkin view`: the viser server on loopback, its scene, sliders, live IK and playback.

The viewer tests need the `viz` extra (viser) and are skipped without it; the missing-extra error and
the import hygiene (``import diffkin`` never imports viser) are tested either way.
"""

from __future__ import annotations

import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import torch

from diffkin import cli, models, viz
from diffkin.viz.scene import _wxyz

ROOT = Path(__file__).resolve().parents[1]


# ------------------------------------------------------------------------------- without the extra
def test_import_diffkin_does_not_import_viser():
    code = "import sys, diffkin, diffkin.viz, diffkin.cli; sys.exit('viser' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], cwd=ROOT).returncode == 0


def test_view_without_viser_names_the_extra(monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "viser", None)  # `import viser` raises ImportError
    assert cli.main(["view", "--robot", "panda"]) == 2
    err = capsys.readouterr().err
    assert err == "error: diffkin view needs the 'viz' extra: pip install 'diffkin[viz]'\n"


def test_view_parser():
    args = cli.build_parser().parse_args(["view", "--urdf", "a.urdf", "--end-link", "l1", "l2"])
    assert args.host == "127.0.0.1" and args.port == 8080 and args.end_link == ["l1", "l2"]
    assert args.func.__module__ == "diffkin.viz.command"


# ------------------------------------------------------------------------------------- the viewer
try:
    import viser
except ImportError:
    viser = None

needs_viser = pytest.mark.skipif(viser is None, reason="needs the viz extra (viser)")


@pytest.fixture(scope="module")
def panda():
    return models.load("panda", dtype=torch.float64)


@pytest.fixture(scope="module")
def viewer(panda):
    v = viz.show(panda, port=0, ik_options={"num_seeds": 16})
    yield v
    v.close()


def _scene_bytes(url: str, timeout: float = 120.0) -> bytes:
    """Connect as a browser would and return the decompressed scene messages the server sends."""
    import zstandard
    from websockets.sync.client import connect

    out = b""
    ws_url = url.replace("http://", "ws://")
    with connect(ws_url, subprotocols=[f"viser-v{viser.__version__}"], open_timeout=timeout) as ws:
        for _ in range(20):
            try:
                raw = ws.recv(timeout=timeout)  # a hang guard: the loop ends on the IK target
            except TimeoutError:
                break
            if isinstance(raw, bytes) and len(raw) > 16:
                n_inner = int.from_bytes(raw[:8], "little")
                n_comp = int.from_bytes(raw[8:16], "little")
                out += zstandard.ZstdDecompressor().decompress(raw[16:16 + n_comp], max_output_size=n_inner)
            if b"/ik/target_0" in out:
                break
    return out


@needs_viser
def test_serves_loopback_http_and_scene(viewer, panda):
    assert viewer.url.startswith("http://127.0.0.1:") and viewer.port > 0
    with urllib.request.urlopen(viewer.url, timeout=120) as r:  # a hang guard, not a time limit
        assert r.status == 200
        page = r.read()
    assert b"<html" in page.lower()
    # server side: the robot's nodes
    names = set(viewer.server.scene._handle_from_node_name)
    J = len(panda.topology.parents)
    assert {"/robot/base", "/robot/segments", "/ik/target_0", *(f"/robot/frame_{i}" for i in
                                                                range(1, J + 1))} <= names
    # over the wire: what a browser receives
    sent = _scene_bytes(viewer.url)
    for node in (b"/robot/segments", b"/robot/frame_1", b"/ik/target_0"):
        assert node in sent


@needs_viser
def test_sliders_set_q_and_frames_follow_fk(viewer, panda):
    q = panda.random_configuration((), generator=torch.Generator().manual_seed(1))
    viewer.set_q(q)
    F = panda.forward_kinematics(q, all_frames=True).detach().numpy()
    np.testing.assert_allclose(viewer.frames(), F, atol=1e-9)
    h = viewer.server.scene.get_handle_by_name("/robot/frame_3")
    np.testing.assert_allclose(h.position, F[3, :3, 3], atol=1e-6)
    assert [s.value for s in viewer.sliders] == pytest.approx(q.tolist(), abs=1e-12)
    seg = viewer._segments.points
    np.testing.assert_allclose(seg[-1, 1], F[-1, :3, 3], atol=1e-5)  # last segment ends at the EE
    # a slider moved in the GUI: q, frames and the IK target follow
    viewer.sliders[1].value = 0.3
    q2 = q.clone()
    q2[1] = 0.3
    assert viewer.q.tolist() == pytest.approx(q2.tolist())
    F2 = panda.forward_kinematics(q2, all_frames=True).detach().numpy()
    np.testing.assert_allclose(viewer.frames(), F2, atol=1e-9)
    np.testing.assert_allclose(viewer._targets[0].position, F2[-1, :3, 3], atol=1e-6)


@needs_viser
def test_moving_the_target_runs_ik(viewer, panda):
    viewer.set_q(torch.tensor([0.0, -0.3, 0.0, -2.0, 0.0, 1.8, 0.8], dtype=torch.float64),
                 move_targets=True)
    q_goal = torch.tensor([0.2, -0.1, 0.1, -1.8, 0.1, 1.7, 0.6], dtype=torch.float64)
    T = panda.forward_kinematics(q_goal).detach().numpy()
    # what a drag in the browser does: the gizmo's pose changes, then its callback runs
    h = viewer._targets[0]
    h.position, h.wxyz = T[:3, 3], _wxyz(T[:3, :3])
    viewer._on_target_event(None)
    assert viewer.ik_state["success"] is True
    assert viewer.ik_state["position_error"] < 1e-4
    assert viewer.gui_ik_success.value == "yes"
    assert float(viewer.gui_ik_position.value) < 0.1  # mm
    assert float(viewer.gui_ik_orientation.value) < 0.06  # deg
    E = panda.forward_kinematics(viewer.q).detach().numpy()
    np.testing.assert_allclose(E, T, atol=1e-3)
    np.testing.assert_allclose(viewer.end_poses()[0], E, atol=1e-9)  # the scene shows the solution
    assert [s.value for s in viewer.sliders] == pytest.approx(viewer.q.tolist(), abs=1e-9)
    # an unreachable target: failure and the errors are shown, the best effort is drawn
    res = viewer.solve_to(np.array([[1, 0, 0, 3.0], [0, 1, 0, 0], [0, 0, 1, 0.5], [0, 0, 0, 1]]))
    assert not bool(res.success) and viewer.gui_ik_success.value == "no (best effort shown)"
    assert viewer.ik_state["message"] == "not reached (best effort shown)"
    assert float(viewer.gui_ik_position.value) > 1000  # mm
    # position only
    res = viewer.solve_to(T, position_only=True)
    assert bool(res.success) and viewer.gui_ik_orientation.value == "-"


@needs_viser
def test_trajectory_playback(viewer, panda, tmp_path):
    traj = panda.random_configuration((6,), generator=torch.Generator().manual_seed(2))
    path = tmp_path / "traj.npy"
    np.save(path, traj.numpy())
    viewer.load_trajectory(path, fps=50)
    assert viewer.frame == 0 and not viewer.playing
    np.testing.assert_allclose(viewer.q.numpy(), traj[0].numpy())
    viewer.step(4)
    assert viewer._traj_gui["frame"].value == 4
    np.testing.assert_allclose(viewer.frames(), panda.forward_kinematics(traj[4], all_frames=True).detach())
    viewer._traj_gui["frame"].value = 2  # the GUI's frame slider
    assert viewer.frame == 2
    np.testing.assert_allclose(viewer.q.numpy(), traj[2].numpy())
    # play to the end without looping: it stops on the last frame
    viewer.play(fps=100, loop=False)
    import time

    t_end = time.monotonic() + 120  # a hang guard: playback ends by itself
    while viewer.playing and time.monotonic() < t_end:
        time.sleep(0.02)
    assert not viewer.playing and viewer.frame == 5
    np.testing.assert_allclose(viewer.q.numpy(), traj[5].numpy())
    assert viewer._traj_gui["play"].label == "Play"
    with pytest.raises(Exception, match="shape"):
        viewer.play(np.zeros((3, 2)))
    # the .npz of `diffkin trajectory joint`: joint positions and times (played at their rate)
    out = tmp_path / "joint.npz"
    start, end = ["0", "0", "0", "-1.5", "0", "1.5", "0"], ["1", "0.5", "0", "-2", "0", "2", "0.5"]
    assert cli.main(["trajectory", "joint", "--start", *start, "--end", *end, "--samples", "21",
                     "--duration", "2", "--output", str(out)]) == 0
    viewer.load_trajectory(out)
    assert viewer._traj.shape == (21, 7) and viewer._fps == pytest.approx(10.0)
    viewer.step(-1)
    np.testing.assert_allclose(viewer.q.numpy(), [float(v) for v in end], atol=1e-12)


@needs_viser
def test_tree_and_urdf_meshes(tmp_path):
    import trimesh

    trimesh.creation.box(extents=(0.05, 0.05, 0.3)).export(tmp_path / "link.stl")
    urdf = tmp_path / "arm.urdf"
    urdf.write_text("""<robot name="arm">
  <link name="base"/>
  <link name="l1"><visual><origin xyz="0 0 0.15"/><geometry><mesh filename="link.stl"/></geometry>
    </visual></link>
  <link name="a"/><link name="b"/>
  <joint name="j1" type="revolute"><parent link="base"/><child link="l1"/><axis xyz="0 0 1"/>
    <limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
  <joint name="ja" type="revolute"><parent link="l1"/><child link="a"/><origin xyz="0 0.1 0.3"/>
    <axis xyz="1 0 0"/><limit lower="-2" upper="2" effort="1" velocity="1"/></joint>
  <joint name="jb" type="continuous"><parent link="l1"/><child link="b"/><origin xyz="0 -0.1 0.3"/>
    <axis xyz="0 1 0"/></joint>
</robot>""")
    chain = models.from_urdf(str(urdf), ["a", "b"], dtype=torch.float64)
    with viz.show(chain, port=0, urdf=urdf) as v:
        assert v.has_meshes
        names = set(v.server.scene._handle_from_node_name)
        assert any(n.startswith("/robot/urdf/") for n in names)
        assert {"/robot/end_0", "/robot/end_1", "/ik/target_0", "/ik/target_1"} <= names
        assert len(v.sliders) == 3 and v.sliders[2].min == pytest.approx(-np.pi)  # continuous: ±π
        q = torch.tensor([0.5, 0.3, -0.4], dtype=torch.float64)
        E = chain.forward_kinematics(q).detach().numpy()  # (2, 4, 4)
        res = v.solve_to(E)  # both end links at once
        assert bool(res.success)
        np.testing.assert_allclose(v.end_poses(), E, atol=1e-3)
    # a mesh that does not resolve: frames and segments only
    urdf.write_text(urdf.read_text().replace('filename="link.stl"', 'filename="package://nowhere/x.stl"'))
    with viz.show(models.from_urdf(str(urdf), "a"), port=0, urdf=urdf) as v:
        assert not v.has_meshes and v.server.scene.get_handle_by_name("/robot/segments") is not None


@needs_viser
def test_cli_view_serves_and_stops(tmp_path, capsys):
    assert cli.main(["view", "--robot", "three_link_planar", "--port", "0", "--duration", "0.5"]) == 0
    out = capsys.readouterr().out
    assert "three_link_planar" in out and "http://127.0.0.1:" in out


@needs_viser
def test_velocity_drag_follows_the_target_within_the_limits(panda):
    v = viz.show(panda, port=0, drag="velocity", drag_speed=1.5)
    try:
        assert v.gui_limit_safe.value is True
        q0 = torch.tensor([0.0, -0.3, 0.0, -2.0, 0.0, 1.8, 2.7], dtype=torch.float64)
        v.set_q(q0, move_targets=True)
        # a small drag: reached, as ik.solve would
        T = panda.forward_kinematics(q0 + torch.tensor([0.1, 0.05, -0.05, 0.1, 0.0, -0.05, 0.0],
                                                       dtype=torch.float64)).detach().numpy()
        h = v._targets[0]
        h.position, h.wxyz = T[:3, 3], _wxyz(T[:3, :3])
        v._on_target_event(None)
        assert v.ik_state["success"] is True and v.ik_state["position_error"] < 1e-4
        np.testing.assert_allclose(panda.forward_kinematics(v.q).detach().numpy(), T, atol=1e-3)
        # a roll of the flange past joint 7's limit: the arm follows within the limits
        R = np.array([[np.cos(0.8), -np.sin(0.8), 0], [np.sin(0.8), np.cos(0.8), 0], [0, 0, 1]])
        T2 = T.copy()
        T2[:3, :3] = T[:3, :3] @ R
        state = v.drag_to(T2)
        assert bool(panda.within_limits(v.q).all())
        assert float(v.q[6]) == pytest.approx(float(panda.q_limits[6, 1]), abs=1e-9)  # joint 7 at its limit
        assert state["orientation_error"] < 1e-3  # the other joints took over the rest of the roll
        assert state is v.ik_state and state["message"] in ("reached", "following (limit-safe)")
        assert v.gui_ik_success.value == ("yes" if state["success"] else "no (following within the limits)")
    finally:
        v.close()


@needs_viser
def test_retargeted_clip_playback(tmp_path):
    """A retargeted clip plays at its rate: a RetargetResult (its human keypoints drawn beside the robot and
    following the frames) and the .npz its save writes (here the shipped G1 walk), on the G1 MJCF chain."""
    from diffkin import retarget

    mp = retarget.Mapping.builtin("g1")
    g1 = models.load_chain("g1", end_link=mp.frames, dtype=torch.float64).requires_grad_(False)
    walk = retarget.load_bvh(retarget.example_clips()["walk"]).frames_slice(0, 5)
    result = retarget.clip(g1, walk, mp, whole_clip=False)
    v = viz.show(g1, port=0, meshes=False)
    try:
        v.load_trajectory(result)
        assert v._traj.shape == (5, g1.n_joints) and v._fps == 60.0
        nodes = set(v.server.scene._handle_from_node_name)
        assert "/retarget/keypoints" in nodes
        v.step(3)
        np.testing.assert_allclose(v.q.numpy(), result.q[0, 3].numpy())
        np.testing.assert_allclose(v.frames(), g1.forward_kinematics(result.q[0, 3], all_frames=True))
        # the cloud holds frame 3's scaled human joints (viser sends float16: within 1 mm at 2 m)
        np.testing.assert_allclose(v._keypoints[1].points, result.keypoints[0, 3].numpy(), atol=1e-3)
        with pytest.raises(Exception, match="clip 1"):
            v.load_trajectory(result, clip=1)
        # the saved .npz: q (B, T, nq) and fps; no keypoints in the file, so the cloud goes
        shipped = retarget.example_clips()["walk"].parent / "g1_walk.npz"
        v.load_trajectory(shipped)
        with np.load(shipped) as data:
            q = data["q"][0]
        assert v._traj.shape == q.shape and v._fps == 60.0 and v._keypoints is None
        assert "/retarget/keypoints" not in set(v.server.scene._handle_from_node_name)
        v.step(-1)
        np.testing.assert_allclose(v.q.numpy(), q[-1])
        path = result.save(tmp_path / "r.npz")
        v.load_trajectory(path)
        np.testing.assert_allclose(v._traj.numpy(), result.q[0].numpy())
    finally:
        v.close()


@needs_viser
def test_planned_motion_playback(tmp_path, capsys):
    """A planned motion plays problem by problem up to its end at its rate 1 / dt: a MotionResult
    (viewer.play(result, problem=i)) and the .npz of `diffkin plan` (load_trajectory(..., problem=i),
    `diffkin view --trajectory plan.npz --problem I --play`); a failed problem says why."""
    import warnings

    from diffkin import motion
    from diffkin.collision import RobotCollision

    fr3 = Path(__file__).parent / "data" / "urdf" / "fr3.urdf"
    srdf = ('<robot name="fr3"><disable_collisions link1="fr3_link1_sc" link2="fr3_link3_sc" '
            'reason="Default"/></robot>')
    chain = models.from_urdf(fr3, "fr3_link8", dtype=torch.float64).requires_grad_(False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        robot = RobotCollision.from_urdf(fr3, chain, srdf=srdf).requires_grad_(False)
    q0 = torch.tensor([[0.8, 0.3, 0.0, -1.8, 0.0, 2.1, 0.785], [3.0, 0.3, 0.0, -1.8, 0.0, 2.1, 0.785],
                       [0.0, 0.0, 0.0, -1.5, 0.0, 1.8, 0.0]], dtype=torch.float64)
    q1 = torch.tensor([[0.2, 0.1, 0.0, -2.0, 0.0, 2.0, 0.5]], dtype=torch.float64).expand(3, -1)
    res = motion.plan(chain, q0, q1, collision=robot, acceleration_limit=5.0, dt=0.02, resolution=0.01)
    assert res.success.tolist() == [True, False, True]
    n = [int(np.ceil(float(d) / 0.02 - 1e-9)) + 1 for d in res.duration]
    assert n[0] != n[2] and res.q.shape[1] == max(n)
    v = viz.show(chain, port=0, meshes=False)
    try:
        v.play(res, problem=2, loop=False)
        assert v._traj.shape == (n[2], 7) and v._fps == pytest.approx(50.0)
        t_end = time.monotonic() + 120  # a hang guard: playback ends by itself
        while v.playing and time.monotonic() < t_end:
            time.sleep(0.02)
        assert not v.playing and v.frame == n[2] - 1
        np.testing.assert_array_equal(v.q.numpy(), q1[0].numpy())  # ends on the goal
        with pytest.raises(Exception, match="problem 1 .*failed .*outside the joint limits"):
            v.load_trajectory(res, problem=1)
        with pytest.raises(Exception, match="problem 3 is not among the 3"):
            v.load_trajectory(res, problem=3)
        # the file `diffkin plan` writes: the same frames, problem 0
        path = tmp_path / "plan.npz"
        np.savez(path, t=res.t.numpy(), q=res.q.numpy(), qd=res.qd.numpy(), qdd=res.qdd.numpy(),
                 success=res.success.numpy(), duration=res.duration.numpy(), reason=np.array(res.reason))
        v.load_trajectory(path, problem=0)
        np.testing.assert_array_equal(v._traj.numpy(), res.q[0, :n[0]].numpy())
        assert v._fps == pytest.approx(50.0)
    finally:
        v.close()
    view = ["view", "--urdf", str(fr3), "--end-link", "fr3_link8", "--no-meshes", "--port", "0", "--duration",
            "0.3", "--trajectory", str(path), "--play"]
    assert cli.main([*view, "--problem", "2"]) == 0
    assert cli.main([*view, "--problem", "1"]) == 2
    assert "problem 1 of" in capsys.readouterr().err

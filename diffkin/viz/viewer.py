"""The viewer itself: :class:`Viewer` (a viser server with the robot, joint sliders, draggable IK targets,
collision colours and trajectory playback) and :func:`show`."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from ..errors import DiffkinError, ShapeError
from .playback import _read_trajectory
from .scene import (
    _KEYPOINT_RGB,
    _SEGMENT_RGB,
    _as_joints,
    _import_viser,
    _maybe_quiet,
    _pose,
    _quiet_logs,
    _wxyz,
    segment_points,
)

__all__ = ["Viewer", "show"]


class Viewer:
    """A viser server showing one chain, its joint sliders, IK targets and trajectory playback.

    Args:
        chain: any :class:`~diffkin.chain.KinematicChain` (DH or URDF, one or K end links).
        q: initial joint vector ``(n,)`` (default: zero where the limits allow, else the middle of the
            joint's range ``chain.lower_upper()``).
        host: interface to serve on (default loopback ``127.0.0.1``; ``0.0.0.0`` for every interface).
        port: TCP port; ``0`` picks a free one; viser moves on to the next free port if it is taken —
            :attr:`port` / :attr:`url` say which one is served.
        trajectory: optional joint vectors ``(N, n)`` (tensor, array or .npy/.npz/.csv) to play back.
        fps: playback frames per second (default: the file's own rate when it has times, else 30).
        urdf: the URDF file of a URDF chain, to show its visual meshes (relative and ``package://`` mesh
            paths resolve against the file's folder; ``None``: against the working directory).
        meshes: False: never load URDF meshes (frames and segments only).
        ik_options: keyword arguments for :func:`diffkin.ik.solve` (e.g. ``num_seeds``, tolerances).
        drag: what a drag of a target runs: ``"solve"`` (:func:`diffkin.ik.solve`, a jump to a solution)
            or ``"velocity"`` (:meth:`drag_to`: limit-safe velocity-IK steps from the current q).
        drag_speed: the joint speed bound of ``"velocity"`` drags (rad/s or m/s, per 0.05 s step).
        verbose: let viser print its banner and connection messages.
        collision: a :class:`~diffkin.collision.RobotCollision` of ``chain`` to draw (pairs in contact red).
        world: a :class:`~diffkin.collision.World` (no batch dims) to draw; geoms touching it are red too.
        margin: a pair is in contact when its signed distance is below this (m; default 0: penetration).

    Attributes:
        server: the ``viser.ViserServer``.
        q: the current joint vector ``(n,)`` (a copy).
        ik_state: the last IK solve: ``success`` (bool), ``position_error`` (m), ``orientation_error``
            (rad), ``time_s``, ``message`` — also shown in the GUI's IK folder.
        has_meshes: whether URDF visual geometry (or MJCF geoms) is shown.
        visual_geoms: the MJCF geoms drawn (:class:`~diffkin.viz.mjcf.VisualGeom`), ``missing_meshes`` the
            mesh geoms not drawn (files not found).
        contacts: the collision state at the shown q (``pairs``, ``world``, ``min_distance``; see
            :meth:`diffkin.viz.collision.CollisionView.update`), ``{}`` without ``collision``.
    """

    def __init__(self, chain, q=None, *, host: str = "127.0.0.1", port: int = 8080, trajectory=None,
                 fps: float | None = None, urdf=None, meshes: bool = True, ik_options: dict | None = None,
                 verbose: bool = False, drag: str = "solve", drag_speed: float = 2.0, collision=None,
                 world=None, margin: float = 0.0):
        if drag not in ("solve", "velocity"):
            raise DiffkinError(f"drag must be 'solve' or 'velocity', got {drag!r}")
        if collision is not None and collision.chain not in (None, chain):
            raise DiffkinError("collision must be a RobotCollision of the chain shown")
        if world is not None and collision is None:
            raise DiffkinError("world needs collision= (the robot's RobotCollision) to be checked against")
        from ..validation import check_number

        margin = check_number(margin, "margin", positive=False, unit=" (m)")
        viser = _import_viser()
        self.chain = chain
        self._collision_args = (collision, world, margin)
        self.ik_options = dict(ik_options or {})
        self._drag, self.drag_speed = drag, float(drag_speed)
        self.ik_state: dict = {"success": None, "position_error": None, "orientation_error": None,
                               "time_s": None, "message": "drag a target to solve IK"}
        self._lock = threading.RLock()
        self._syncing = False
        self._closed = False
        topo = chain.topology
        self._parents = list(topo.parents)
        self._end_frames = [e + 1 for e in topo.ends]  # frame index each end link hangs from
        self._single_end = chain.single_end
        J = len(self._parents)
        # a single end link whose pose is the last frame needs no separate end node
        self._ends_in_frames = self._single_end and topo.ends[0] == J - 1
        lo, hi = chain.lower_upper()
        self._lo, self._hi = lo.detach().cpu().double().numpy(), hi.detach().cpu().double().numpy()
        if q is None:  # zero where the limits allow it, else the middle of the joint's range
            q = np.where((self._lo <= 0) & (self._hi >= 0), 0.0, 0.5 * (self._lo + self._hi))
        self._q = _as_joints(chain, q)
        if not chain.configuration_space.euclidean:  # quaternions: unit, identity where the default put 0
            self._q = chain.normalize_configuration(self._q)
        self._q_ref = self._q.clone()

        with _maybe_quiet(verbose):  # viser prints its URL banner whatever `verbose` says
            self.server = viser.ViserServer(host=host, port=port, verbose=verbose)
        self._verbose = verbose
        self.host = host
        try:
            self._build_scene(urdf, meshes)
            self._build_gui()
            self._traj: Tensor | None = None
            self._traj_gui: dict = {}
            self._keypoints: tuple | None = None  # a retargeted clip's human keypoints (N, K, 3), cloud
            self._playing = threading.Event()
            self._fps = 30.0 if fps is None else float(fps)
            self._frame = 0
            self._loop = True
            self._player = threading.Thread(target=self._play_loop, name="diffkin-viz-player", daemon=True)
            self._player.start()
            self._ik_pending: np.ndarray | None = None
            self._ik_busy = False
            self.set_q(self._q)
            if trajectory is not None:
                self.load_trajectory(trajectory, fps=fps)
        except BaseException:
            with _maybe_quiet(verbose):
                self.server.stop()
            raise

    # ----------------------------------------------------------------------------------- properties
    @property
    def port(self) -> int:
        """The TCP port actually served."""
        return int(self.server.get_port())

    @property
    def url(self) -> str:
        """``http://host:port`` of the viewer (loopback address when serving on every interface)."""
        host = "127.0.0.1" if self.host in ("0.0.0.0", "") else self.host
        return f"http://{host}:{self.port}"

    @property
    def q(self) -> Tensor:
        """The current joint vector ``(n,)`` (chain dtype and device; a copy)."""
        with self._lock:
            return self._q.clone()

    # ----------------------------------------------------------------------------------------- scene
    def _fk(self, q: Tensor) -> tuple[np.ndarray, np.ndarray]:
        """(frames (J + 1, 4, 4), end poses (K, 4, 4)) as float64 arrays."""
        with torch.no_grad():
            F = self.chain.forward_kinematics(q, all_frames=True)
            E = self.chain.forward_kinematics(q).reshape(-1, 4, 4)
        return F.detach().cpu().double().numpy(), E.detach().cpu().double().numpy()

    def _segment_points(self, F: np.ndarray, E: np.ndarray) -> np.ndarray:
        return segment_points(self.chain, F, E).astype(np.float32)

    def _build_scene(self, urdf, meshes: bool) -> None:
        scene = self.server.scene
        F, E = self._fk(self._q)
        pts = np.concatenate([F[:, :3, 3], E[:, :3, 3]])
        reach = float(np.linalg.norm(pts - F[0, :3, 3], axis=-1).max())
        seg = self._segment_points(F, E)
        if self._single_end:  # a folded arm can look tiny: also half its length, base to end
            reach = max(reach, 0.5 * float(np.linalg.norm(seg[:, 1] - seg[:, 0], axis=-1).sum()))
        reach = max(reach, 0.05)
        self.scale = reach
        s = reach
        scene.set_up_direction("+z")
        scene.add_grid("/grid", width=2.5 * s, height=2.5 * s, cell_size=s / 10, section_size=s / 2,
                       position=tuple(F[0, :3, 3]))
        # look at the middle of the robot's bounding box from the front right, far enough to see all of it
        lo_b, hi_b = pts.min(axis=0), pts.max(axis=0)
        centre = 0.5 * (lo_b + hi_b)
        size = max(float(np.linalg.norm(hi_b - lo_b)), 0.3 * s)
        view = np.array([1.0, 0.8, 0.45])
        self.server.initial_camera.position = tuple(centre + 1.1 * size * view / np.linalg.norm(view))
        self.server.initial_camera.look_at = tuple(centre)
        self.server.initial_camera.up = (0.0, 0.0, 1.0)
        self._frames = []
        for i in range(F.shape[0]):
            base = i == 0
            self._frames.append(scene.add_frame(
                "/robot/base" if base else f"/robot/frame_{i}",
                axes_length=(0.12 if base else 0.06) * s, axes_radius=0.005 * s, origin_radius=0.016 * s,
            ))
        self._end_handles = []
        if not self._ends_in_frames:
            for k in range(E.shape[0]):
                self._end_handles.append(scene.add_frame(
                    f"/robot/end_{k}", axes_length=0.09 * s, axes_radius=0.006 * s, origin_radius=0.02 * s,
                ))
        self._segments = scene.add_line_segments("/robot/segments", seg, colors=_SEGMENT_RGB,
                                                 thickness=0.022 * s)
        self._mesh = None
        if meshes:
            self._mesh = self._load_meshes(urdf)
        self._add_mjcf_geoms(meshes)
        self.has_meshes = self._mesh is not None or bool(self.visual_geoms)
        self._collision_view = None
        if self._collision_args[0] is not None:
            from .collision import CollisionView

            self._collision_view = CollisionView(scene, *self._collision_args, scale=s, q=self._q)
        self._targets = []
        for k in range(E.shape[0]):
            h = scene.add_transform_controls(f"/ik/target_{k}", scale=0.18 * s, depth_test=False,
                                             wxyz=_wxyz(E[k, :3, :3]), position=tuple(E[k, :3, 3]))
            h.on_update(self._on_target_event)
            self._targets.append(h)

    def _add_mjcf_geoms(self, meshes: bool) -> None:
        """One scene node per MuJoCo body holding its geoms (an MJCF chain only)."""
        self.visual_geoms, self.missing_meshes, self._body_nodes = [], [], {}
        if not (hasattr(self.chain, "to_qpos") and hasattr(self.chain, "source_text")):
            return
        from .mjcf import mjcf_visuals

        with _quiet_logs():
            self.visual_geoms, self.missing_meshes = mjcf_visuals(self.chain, meshes=meshes)
        scene = self.server.scene
        for b in sorted({g.body for g in self.visual_geoms}):
            self._body_nodes[b] = scene.add_frame(f"/mjcf/body_{b}", show_axes=False)
        self._geom_handles = [
            scene.add_mesh_simple(f"/mjcf/body_{g.body}/geom_{i}", g.vertices, g.faces, color=g.rgb,
                                  opacity=g.opacity if g.opacity < 1.0 else None,
                                  position=g.local[:3, 3], wxyz=_wxyz(g.local[:3, :3]))
            for i, g in enumerate(self.visual_geoms)]

    def geom_poses(self) -> np.ndarray:
        """World poses ``(G, 4, 4)`` of the MJCF geoms as the scene holds them (body node ∘ geom node), in the
        order of :attr:`visual_geoms`."""
        with self._lock:
            out = [_pose(self._body_nodes[g.body].wxyz, self._body_nodes[g.body].position)
                   @ _pose(h.wxyz, h.position) for g, h in zip(self.visual_geoms, self._geom_handles)]
        return np.stack(out) if out else np.zeros((0, 4, 4))

    @property
    def contacts(self) -> dict:
        with self._lock:
            return dict(self._collision_view.state) if self._collision_view is not None else {}

    def _load_meshes(self, urdf):
        """ViserUrdf of the chain's URDF when at least one visual mesh file resolves (or the visuals are
        primitives), else None (frames and segments only)."""
        tree = getattr(self.chain, "tree", None)
        if tree is None or self.chain.root_link != tree.root:
            return None
        try:
            import io

            import yourdfpy
            from viser.extras import ViserUrdf
        except ImportError:
            return None
        folder = Path(urdf).resolve().parent if urdf is not None else Path.cwd()

        def handler(fname: str) -> str:
            return yourdfpy.filename_handler_magic(fname, dir=str(folder))

        try:
            with _quiet_logs():
                bare = yourdfpy.URDF.load(io.StringIO(tree.text), build_scene_graph=False, load_meshes=False)
                shown = 0
                for link in bare.robot.links:
                    for v in link.visuals:
                        g = v.geometry
                        if g is None:
                            continue
                        if g.mesh is not None:
                            shown += Path(handler(g.mesh.filename)).is_file()
                        elif g.box is not None or g.cylinder is not None or g.sphere is not None:
                            shown += 1
                if not shown:
                    return None
                model = yourdfpy.URDF.load(io.StringIO(tree.text), build_scene_graph=True, load_meshes=True,
                                           filename_handler=handler)
                vis = ViserUrdf(self.server, model, root_node_name="/robot/urdf")
        except Exception:  # a URDF yourdfpy cannot read: frames and segments still show the robot
            return None
        names = list(vis.get_actuated_joint_names())
        index = {name: i for i, name in enumerate(self.chain.joint_names)}
        self._mesh_map = [(j, index.get(name)) for j, name in enumerate(names)]
        self._mesh_cfg = np.zeros(len(names))
        return vis

    def _update_scene(self) -> None:
        F, E = self._fk(self._q)
        qw = _wxyz(F[:, :3, :3])
        with self.server.atomic():
            for h, T, w in zip(self._frames, F, qw):
                h.position, h.wxyz = T[:3, 3], w
            if self._end_handles:
                ew = _wxyz(E[:, :3, :3])
                for h, T, w in zip(self._end_handles, E, ew):
                    h.position, h.wxyz = T[:3, 3], w
            self._segments.points = self._segment_points(F, E)
            if self._mesh is not None:
                qn = self._q.detach().cpu().double().numpy()
                for j, i in self._mesh_map:
                    self._mesh_cfg[j] = qn[i] if i is not None else 0.0
                base = self.server.scene.get_handle_by_name("/robot/urdf")
                if base is not None:
                    base.position, base.wxyz = F[0, :3, 3], qw[0]
                self._mesh.update_cfg(self._mesh_cfg)
            if self._body_nodes:
                from ..models.mjcf_bodies import body_poses

                with torch.no_grad():
                    B = body_poses(self.chain, self._q).detach().cpu().double().numpy()
                bw = _wxyz(B[:, :3, :3])
                for b, h in self._body_nodes.items():
                    h.position, h.wxyz = B[b, :3, 3], bw[b]
            if self._collision_view is not None:
                self._collision_view.update(self._q)
                self._show_contacts()
        self._F, self._E = F, E

    def frames(self) -> np.ndarray:
        """The frames drawn now, ``(J + 1, 4, 4)`` float64: base and joint frames (FK of :attr:`q`)."""
        with self._lock:
            return self._F.copy()

    def end_poses(self) -> np.ndarray:
        """The end-link poses drawn now, ``(K, 4, 4)`` float64 (K = 1 for a single end link)."""
        with self._lock:
            return self._E.copy()

    # ------------------------------------------------------------------------------------------- GUI
    def _build_gui(self) -> None:
        gui = self.server.gui
        chain = self.chain
        gui.configure_theme(control_width="medium")
        from .joints import slider_specs, slider_values

        self._slider_specs = slider_specs(chain, self._lo, self._hi)
        with gui.add_folder("Joints"):
            self.sliders = []
            for spec, value in zip(self._slider_specs, slider_values(self._slider_specs, self._q)):
                s = gui.add_slider(f"{spec.label} [{spec.unit}]", min=spec.lo, max=spec.hi, step=1e-3,
                                   initial_value=float(np.clip(value, spec.lo, spec.hi)))
                s.on_update(self._slider_callback)
                self.sliders.append(s)
            b = gui.add_button("Random configuration")
            b.on_click(lambda _: self.set_q(self.chain.random_configuration(()), move_targets=True))
        with gui.add_folder("Inverse kinematics"):
            self.gui_position_only = gui.add_checkbox("Position only", initial_value=False)
            self.gui_limit_safe = gui.add_checkbox("Limit-safe drag (velocity IK)",
                                                   initial_value=self._drag == "velocity")
            self.gui_ik_success = gui.add_text("Success", initial_value="-", disabled=True)
            self.gui_ik_position = gui.add_text("Position error [mm]", initial_value="-", disabled=True)
            self.gui_ik_orientation = gui.add_text("Orientation error [deg]", initial_value="-",
                                                   disabled=True)
            self.gui_ik_time = gui.add_text("Solve time [ms]", initial_value="-", disabled=True)
            b = gui.add_button("Target to end effector")
            b.on_click(lambda _: self.targets_to_ends())
        if self._collision_args[0] is not None:
            with gui.add_folder("Collision"):
                self.gui_contacts = gui.add_text("Pairs in contact", initial_value="-", disabled=True)
                self.gui_min_distance = gui.add_text("Min distance [mm]", initial_value="-", disabled=True)
        gui.add_markdown(f"**{chain.name}** · {chain.n_joints} joints ({chain.joint_types}) · "
                         f"{len(self._targets)} end link(s) · drag the gizmo to solve IK")

    def _slider_callback(self, _event) -> None:
        """A slider moved: q = chain.integrate(q_ref, v) of all sliders (:mod:`diffkin.viz.joints`)."""
        if self._syncing:
            return
        from .joints import q_of_sliders

        with self._lock:
            q = q_of_sliders(self.chain, self._q_ref, [s.value for s in self.sliders], self._slider_specs)
            self._show(q, move_targets=True, reference=False)

    def _show_contacts(self) -> None:
        st = self._collision_view.state
        pairs = [f"{a}-{b}" for a, b, _ in st["pairs"]] + [f"{g}-world[{j}]" for g, j, _ in st["world"]]
        self.gui_contacts.value = ", ".join(pairs[:6]) + (f" (+{len(pairs) - 6})" if len(pairs) > 6 else "") \
            if pairs else "none"
        self.gui_min_distance.value = f"{st['min_distance'] * 1e3:.1f}"

    # ------------------------------------------------------------------------------------------- API
    def set_q(self, q, move_targets: bool = False) -> None:
        """Show the joint vector ``q`` ``(n,)`` (tensor, array or sequence; rad / m): frames, segments,
        meshes and sliders; ``move_targets`` also puts the IK targets on the end links. Quaternions of
        ball and free joints are normalised; the rotation sliders restart at 0 from this q."""
        q = _as_joints(self.chain, q)
        if not self.chain.configuration_space.euclidean:
            q = self.chain.normalize_configuration(q)
        self._show(q, move_targets=move_targets, reference=True)

    def _show(self, q: Tensor, move_targets: bool, reference: bool) -> None:
        from .joints import slider_values

        with self._lock:
            self._q = q.clone()
            if reference:
                self._q_ref = q.clone()
            self._update_scene()
            self._syncing = True
            try:
                values = slider_values(self._slider_specs, q)
                for s, spec, v in zip(self.sliders, self._slider_specs, values):
                    if reference or spec.q is not None:
                        s.value = float(np.clip(v, spec.lo, spec.hi))
            finally:
                self._syncing = False
            if move_targets:
                self.targets_to_ends()

    def targets_to_ends(self) -> None:
        """Move the IK targets onto the current end-link poses."""
        with self._lock:
            E = self._E
            w = _wxyz(E[:, :3, :3])
            for h, T, wk in zip(self._targets, E, w):
                h.position, h.wxyz = T[:3, 3], wk

    def targets(self) -> np.ndarray:
        """The IK targets' poses ``(K, 4, 4)`` float64, as the transform controls hold them."""
        return np.stack([_pose(h.wxyz, h.position) for h in self._targets])

    def solve_to(self, T_target=None, position_only: bool | None = None):
        """Solve IK to ``T_target`` — ``(4, 4)`` for one end link, ``(K, 4, 4)`` for K (default: where the
        targets are) — seeded from the current q; moves the targets there, shows the solution and its
        errors, and returns the :class:`~diffkin.ik.IKResult` (``q (n,)``, ``success``, errors)."""
        from ..ik import solve

        with self._lock:
            T = self.targets() if T_target is None else self._move_targets(T_target)
            pos_only = bool(self.gui_position_only.value) if position_only is None else position_only
            Tt = torch.as_tensor(T, dtype=self.chain.dtype, device=self.chain.device)
            if self._single_end:
                Tt = Tt[0]
            target = Tt[..., :3, 3] if pos_only else Tt
            t0 = time.perf_counter()
            res = solve(self.chain, target, q0=self._q, position_only=pos_only, **self.ik_options)
            dt = time.perf_counter() - t0
            self.set_q(res.q.detach())
            ok = bool(res.success)
            pe, oe = float(res.position_error.max()), float(res.orientation_error.max())
            self._show_ik(ok, pe, oe, pos_only, dt, "not reached (best effort shown)", "best effort shown")
            return res

    def _show_ik(self, ok: bool, pe: float, oe: float, pos_only: bool, dt: float, message: str,
                 shown: str) -> None:
        """Set :attr:`ik_state` and the IK panel: reached or not (``message`` / ``shown`` say what is shown
        when not), the position (mm) and orientation (deg) errors, the time (ms)."""
        self.ik_state = {"success": ok, "position_error": pe, "orientation_error": None if pos_only else oe,
                         "time_s": dt, "message": "reached" if ok else message}
        self.gui_ik_success.value = "yes" if ok else f"no ({shown})"
        self.gui_ik_position.value = f"{pe * 1e3:.3f}"
        self.gui_ik_orientation.value = "-" if pos_only else f"{np.degrees(oe):.3f}"
        self.gui_ik_time.value = f"{dt * 1e3:.1f}"

    def drag_to(self, T_target=None, position_only: bool | None = None, steps: int = 40,
                dt: float = 0.05) -> dict:
        """Follow the targets (default: where they are; ``(4, 4)`` / ``(K, 4, 4)`` poses, which moves them)
        from the current q by at most ``steps`` resolved-rate steps q ← q + q̇Δt of
        :func:`diffkin.ik.velocity_step` for the twist that would close the pose error (position,
        axis-angle orientation (3.85)) in one step, bounded by the joint limits and ``drag_speed``: every
        intermediate q is within the limits. Shows and returns :attr:`ik_state`."""
        with self._lock:
            T = self.targets() if T_target is None else self._move_targets(T_target)
            pos_only = bool(self.gui_position_only.value) if position_only is None else position_only
            t0 = time.perf_counter()
            q, pe, oe = _drag_steps(self.chain, self._q, T, pos_only, self.drag_speed, steps, dt)
            self.set_q(q)
            ok = pe < 1e-4 and (pos_only or oe < 1e-3)
            self._show_ik(ok, pe, oe, pos_only, time.perf_counter() - t0, "following (limit-safe)",
                          "following within the limits")
            return self.ik_state

    def _move_targets(self, T_target) -> np.ndarray:
        """Put the targets at ``T_target`` ``(4, 4)`` / ``(K, 4, 4)``; returns the poses ``(K, 4, 4)``."""
        K = len(self._targets)
        T = np.asarray(T_target.detach().cpu() if isinstance(T_target, Tensor) else T_target,
                       dtype=np.float64).reshape(-1, 4, 4)
        if T.shape[0] != K:
            raise ShapeError(f"T_target: expected {K} pose(s) of shape (4, 4), got {T.shape[0]}")
        for h, Tk, wk in zip(self._targets, T, _wxyz(T[:, :3, :3])):
            h.position, h.wxyz = Tk[:3, 3], wk
        return T

    def _on_target_event(self, _event) -> None:
        """Transform-controls callback: solve for the newest target pose; drags that arrive while a solve
        runs are merged into one more solve."""
        with self._lock:
            self._ik_pending = self.targets()
            if self._ik_busy:
                return
            self._ik_busy = True
        try:
            while True:
                with self._lock:
                    T, self._ik_pending = self._ik_pending, None
                    if T is None or self._closed:
                        self._ik_busy = False
                        return
                    if self.gui_limit_safe.value:
                        self.drag_to(None)
                    else:
                        self.solve_to(None)
        except BaseException:
            with self._lock:
                self._ik_busy = False
            raise

    # ------------------------------------------------------------------------------------ trajectory
    def load_trajectory(self, trajectory, fps: float | None = None, clip: int = 0, problem: int = 0) -> None:
        """Load joint vectors ``(N, n)`` for playback (paused, at frame 0) and add the GUI's Trajectory
        folder (play/pause, frame slider, fps). ``trajectory``: a tensor or array, or a ``.npy`` / ``.csv``
        / ``.npz`` (entry ``q``) file, or the ``.npz`` of ``diffkin trajectory joint`` (played at the rate of
        its times ``t`` unless ``fps`` is given), or a retargeted clip: a
        :class:`~diffkin.retarget.RetargetResult` (clip ``clip`` at its rate, its scaled human keypoints
        drawn as green points, ``/retarget/keypoints``, following the frames) or the ``.npz`` its ``save``
        writes (clip ``clip`` at its rate), or a planned motion: a :class:`~diffkin.motion.MotionResult` or
        the ``.npz`` of ``diffkin plan`` (problem ``problem`` up to its end, at its rate 1 / dt)."""
        traj, file_fps, points = _read_trajectory(self.chain, trajectory, clip, problem)
        fps = fps if fps is not None else file_fps
        gui = self.server.gui
        with self._lock:
            self._playing.clear()
            if "folder" in self._traj_gui:
                self._traj_gui["folder"].remove()  # and its controls
            if self._keypoints is not None:
                self._keypoints[1].remove()
                self._keypoints = None
            if points is not None:
                cloud = self.server.scene.add_point_cloud(
                    "/retarget/keypoints", points=points[0].astype(np.float32),
                    colors=np.array(_KEYPOINT_RGB, dtype=np.uint8), point_size=0.03)
                self._keypoints = (points, cloud)
            self._traj, self._frame = traj, 0
            if fps is not None:
                self._fps = float(np.clip(fps, 0.1, 240.0))
            N = traj.shape[0]
            folder = gui.add_folder("Trajectory")
            with folder:
                play = gui.add_button("Play")
                frame = gui.add_slider("Frame", min=0, max=max(N - 1, 1), step=1, initial_value=0,
                                       disabled=N == 1)
                fps_h = gui.add_number("Frames per second", initial_value=self._fps, min=0.1, max=240.0)
                loop = gui.add_checkbox("Loop", initial_value=self._loop)
            play.on_click(lambda _: self.pause() if self._playing.is_set() else self.play())
            frame.on_update(lambda _: None if self._syncing else self.step(int(frame.value)))
            fps_h.on_update(lambda _: setattr(self, "_fps", max(float(fps_h.value), 0.1)))
            loop.on_update(lambda _: setattr(self, "_loop", bool(loop.value)))
            self._traj_gui = {"folder": folder, "play": play, "frame": frame, "fps": fps_h, "loop": loop}
            self.step(0)

    @property
    def frame(self) -> int:
        """Index of the trajectory frame shown."""
        return self._frame

    @property
    def playing(self) -> bool:
        return self._playing.is_set()

    def step(self, i: int) -> None:
        """Show trajectory frame ``i`` (wrapped modulo N)."""
        with self._lock:
            if self._traj is None:
                raise DiffkinError("no trajectory loaded: call play(trajectory) or load_trajectory(...)")
            i = int(i) % self._traj.shape[0]
            self._frame = i
            self.set_q(self._traj[i], move_targets=True)
            if self._keypoints is not None:
                self._keypoints[1].points = self._keypoints[0][i].astype(np.float32)
            self._syncing = True
            try:
                self._traj_gui["frame"].value = i
            finally:
                self._syncing = False

    def play(self, trajectory=None, fps: float | None = None, loop: bool | None = None,
             clip: int = 0, problem: int = 0) -> None:
        """Start playback — of ``trajectory`` if given (what :meth:`load_trajectory` takes, ``clip`` of a
        retargeted clip, ``problem`` of a planned motion), else of the loaded one — at ``fps`` frames per
        second; ``loop`` repeats it (default: the GUI's setting)."""
        if trajectory is not None:
            self.load_trajectory(trajectory, fps=fps, clip=clip, problem=problem)
        elif fps is not None:
            self._fps = float(np.clip(fps, 0.1, 240.0))
        if self._traj is None:
            raise DiffkinError("no trajectory loaded: call play(trajectory)")
        if loop is not None:
            self._loop = bool(loop)
            self._traj_gui["loop"].value = self._loop
        self._traj_gui["fps"].value = self._fps
        if self._frame >= self._traj.shape[0] - 1 and not self._loop:
            self.step(0)
        self._traj_gui["play"].label = "Pause"
        self._playing.set()

    def pause(self) -> None:
        """Stop playback at the current frame."""
        self._playing.clear()
        if "play" in self._traj_gui:
            self._traj_gui["play"].label = "Play"

    def _play_loop(self) -> None:
        while not self._closed:
            if not self._playing.wait(timeout=0.2):
                continue
            t0 = time.perf_counter()
            with self._lock:
                if self._traj is None or not self._playing.is_set():
                    continue
                nxt = self._frame + 1
                if nxt >= self._traj.shape[0] and not self._loop:
                    self.pause()
                    continue
                self.step(nxt)
            time.sleep(max(0.0, 1.0 / self._fps - (time.perf_counter() - t0)))

    # -------------------------------------------------------------------------------------- lifetime
    def close(self) -> None:
        """Stop playback and the server (its port is freed)."""
        if self._closed:
            return
        self._closed = True
        self._playing.set()  # wake the player so it sees _closed
        self._player.join(timeout=2.0)
        with _maybe_quiet(self._verbose):
            self.server.stop()

    def __enter__(self) -> Viewer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        state = "closed" if self._closed else self.url
        return f"Viewer({self.chain.name!r}, {state})"


def _drag_steps(chain, q: Tensor, T: np.ndarray, position_only: bool, speed: float, steps: int, dt: float):
    """Resolved-rate steps of :func:`diffkin.ik.velocity_step` towards the poses ``T (K, 4, 4)``: the twist
    [e_p; e_O]/Δt, |q̇| ≤ speed, the joint limits over Δt. -> (q, position error, orientation error)."""
    from ..ik import velocity_step
    from ..kernels.pose_error import orientation_error

    Tt = torch.as_tensor(T, dtype=chain.dtype, device=chain.device)
    weight = torch.tensor([1.0] * 3 + [0.0 if position_only else 1.0] * 3, dtype=Tt.dtype, device=Tt.device)
    pe = oe = float("inf")
    for k in range(steps + 1):
        E = chain.forward_kinematics(q).detach().reshape(-1, 4, 4)
        e_p = Tt[:, :3, 3] - E[:, :3, 3]
        e_o = orientation_error(Tt[:, :3, :3], E[:, :3, :3], "axis_angle")[0]
        pe, oe = float(e_p.norm(dim=-1).max()), float(e_o.norm(dim=-1).max())
        if k == steps or (pe < 1e-5 and (position_only or oe < 1e-4)):
            break
        twist = torch.cat((e_p, e_o), -1) / dt
        qd = velocity_step(chain, q, twist[0] if chain.single_end else twist, dt, velocity_limit=speed,
                           weight=weight if chain.single_end else weight.expand(len(T), 6))
        q = chain.integrate(q, qd.detach() * dt)  # on the manifold: ball and free joints stay unit
    return q, pe, oe


def show(chain, q=None, *, host: str = "127.0.0.1", port: int = 8080, trajectory=None, **kwargs) -> Viewer:
    """Serve an interactive view of ``chain`` and return its :class:`Viewer` (the server runs in background
    threads; in a notebook, open :attr:`Viewer.url`). ``q`` ``(n,)``: initial configuration; ``trajectory``
    ``(N, n)``: joint vectors to play back; other keyword arguments as for :class:`Viewer`.

    Raises :class:`~diffkin.errors.DiffkinError` (:data:`~diffkin.viz.MISSING_EXTRA`) without viser.
    """
    return Viewer(chain, q, host=host, port=port, trajectory=trajectory, **kwargs)

"""Interactive 3D viewer with live IK, in the browser (`viser <https://viser.studio>`_; the ``viz`` extra).

:func:`show` (Python, notebooks) and ``diffkin view`` (command line) start a viser server — on the
loopback interface unless told otherwise — that shows a :class:`~diffkin.chain.KinematicChain`:

* the robot as link frames and segments between consecutive joint origins, from
  ``chain.forward_kinematics(q, all_frames=True)`` ``(J + 1, 4, 4)`` (base, the J joint frames; for several
  end links the K end poses of ``chain.forward_kinematics(q)`` are added), plus the URDF's own visual
  geometry when its meshes resolve (``yourdfpy``; ``package://`` paths often do not — then only frames and
  segments are drawn);
* for an MJCF chain (:func:`diffkin.models.from_mjcf`), every body's visual geoms in its frame
  (:func:`diffkin.viz.mjcf.mjcf_visuals`: primitives, and meshes where their files resolve, decimated);
* with ``collision=`` (a :class:`~diffkin.collision.RobotCollision`) and ``world=``, the collision geoms and
  the world's objects, red for the pairs in contact (signed distance below ``margin``) at the shown q
  (:mod:`diffkin.viz.collision`);
* one slider per joint variable (range ``chain.lower_upper()``: the limits, ±π / ±1 m where there is none);
  ball joints and the rotation of free joints as three rotation-vector sliders integrated on the manifold
  by ``chain.integrate`` (:mod:`diffkin.viz.joints`), so quaternions stay unit;
* a draggable target per end link (transform controls): moving it runs :func:`diffkin.ik.solve` seeded from
  the current ``q`` and shows success, position and orientation errors and the solve time; with
  ``drag="velocity"`` (or the GUI's "Limit-safe drag" box) the arm instead follows the target by
  resolved-rate steps of :func:`diffkin.ik.velocity_step` (a continuous motion that never leaves the
  joint limits nor exceeds ``drag_speed``);
* trajectory playback of joint vectors ``(N, n)`` (play/pause, a frame slider, frames per second), and of
  a retargeted human clip (a :class:`~diffkin.retarget.RetargetResult`, its human keypoints drawn beside
  the robot, or the ``.npz`` its ``save`` writes), at the clip's frame rate, and of a planned motion (a
  :class:`~diffkin.motion.MotionResult` or the ``.npz`` of ``diffkin plan``: one problem up to its end, at
  its rate 1 / dt).

Nothing here imports viser until a viewer is made: ``import diffkin`` and ``import diffkin.viz`` work
without the extra, and :func:`show` raises :class:`~diffkin.errors.DiffkinError` naming it.

Example::

    import diffkin.viz
    from diffkin import models

    viewer = diffkin.viz.show(models.load("panda"))       # http://127.0.0.1:8080
    viewer.set_q([0, -0.5, 0, -2.0, 0, 1.6, 0.8])         # (n,)
    viewer.solve_to(T_target)                            # (4, 4): IK, seeded from the current q
    viewer.play(trajectory, fps=30)                       # (N, n) tensor / array, or a .npy/.npz/.csv file
    viewer.play(motion.plan(...), problem=2)              # a planned motion, at its rate
    viewer.close()
"""

from __future__ import annotations

from .command import add_parser, cmd_view
from .scene import MISSING_EXTRA, segment_points
from .viewer import Viewer, show

__all__ = ["Viewer", "show", "add_parser", "cmd_view", "segment_points", "MISSING_EXTRA"]

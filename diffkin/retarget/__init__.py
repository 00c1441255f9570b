"""Human motion onto humanoids (issue 37): clips in (:class:`Motion`, :func:`load_bvh`, :func:`load_smpl`,
:func:`example_clips`), robot-human pairings (:class:`Mapping`), foot contacts (:func:`detect_contacts`),
foot soles (:class:`Sole`), the artefact metrics of a robot clip (:func:`metrics`) and retargeting
(:func:`clip`: per-clip scale, a frame-by-frame warm start, then :func:`optimize_clip` over all frames of
all clips at once). See docs/retargeting.md.
"""

from .bvh import load_bvh
from .clip import RetargetResult, clip, fit_scale
from .clips import example_clips
from .contacts import detect_contacts
from .mapping import Mapping, skeleton_of
from .metrics import Metrics, metrics
from .motion import Motion
from .plot import plot_frame
from .self_collision import g1_collision
from .smpl import SMPL_JOINT_NAMES, SMPLX_JOINT_NAMES, load_smpl
from .sole import Sole, sole_of
from .whole_clip import COSTS, ClipOptimization, optimize_clip

__all__ = ["COSTS", "ClipOptimization", "Mapping", "Metrics", "Motion", "RetargetResult", "SMPLX_JOINT_NAMES",
           "SMPL_JOINT_NAMES", "Sole", "clip", "detect_contacts", "example_clips", "fit_scale",
           "g1_collision", "load_bvh", "load_smpl", "metrics", "optimize_clip", "plot_frame",
           "skeleton_of", "sole_of"]

"""Fuzz cases of the viewer's model helpers (issue 26 item 7, issue 27 item 3; see ``tests/fuzzing.py``).

``body_poses(chain, q)`` takes the tensor input; the others read files or are records, and their bad input
is unit-tested in ``tests/test_viz_mjcf.py``.
"""

from __future__ import annotations

from diffkin.models.mjcf_bodies import body_poses
from tests.fuzz_cases_robots import floating, joints
from tests.fuzzing import Arg, Case

#: modules whose every public callable must have a case or an exemption
MODULES: list[str] = ["diffkin.models.mjcf_bodies", "diffkin.viz.mjcf"]

CASES: list[Case] = [
    # the ball + free joint model: q (..., 22); every body of its model, world first
    Case("mjcf_bodies.body_poses", body_poses, {"q": Arg(joints(floating), (22,))}, chain=floating,
         follows_chain=True),
]

_FILES = ("reads an MJCF file or chain (no tensor input); its bad inputs are unit-tested in "
          "tests/test_viz_mjcf.py")
EXEMPT: dict[str, str] = {
    "diffkin.models.mjcf_bodies.body_names": _FILES,
    "diffkin.viz.mjcf.mjcf_visuals": _FILES,
    "diffkin.viz.mjcf.VisualGeom": "a record of one drawn geom (arrays and names), built by mjcf_visuals",
}

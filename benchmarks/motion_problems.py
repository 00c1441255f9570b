"""The 700 MotionBenchMaker Panda problems as VAMP ships them (``tests/data/vamp_panda/problems.tar.bz2``).

The archive holds ``problems/<family>_panda/scene%04d.yaml`` and ``request%04d.yaml`` for 7 families
(``bookshelf_small``, ``bookshelf_tall``, ``bookshelf_thin``, ``box``, ``cage``, ``table_pick``,
``table_under_pick``) × 100 problems: a scene is a MoveIt PlanningScene (obstacles, the allowed-collision
matrix; read by :func:`diffkin.collision.moveit.read_scene`), a request a MoveIt MotionPlanRequest (start
joint state, goal joint constraints). Format and provenance: ``tests/data/vamp_panda/README.md``.

    for p in iter_problems():               # MotionProblem(family, index, scene, start, goal, ...)
        world = p.scene.to_world(dtype=torch.float64)
        rc_p = rc.allow_collisions(p.scene.allowed)

Reads the archive as it is (no extraction to disk), in family order then index order, the way VAMP's
``resources/problem_tar_to_pkl_json.py`` pairs scenes and requests (by the number in the file name).
"""

from __future__ import annotations

import re
import tarfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import yaml

from diffkin.collision.moveit import Scene, scene_from_data

FRANKA_V = [2.175, 2.175, 2.175, 2.175, 2.61, 2.61, 2.61]
FRANKA_A = [15.0, 7.5, 10.0, 12.5, 15.0, 20.0, 20.0]
FRANKA_J = [7500.0, 3750.0, 5000.0, 6250.0, 7500.0, 10000.0, 10000.0]

__all__ = ["DATA", "ARCHIVE", "PANDA_URDF", "PANDA_SPHERIZED_URDF", "PANDA_SRDF", "PANDA_JOINTS",
           "MotionProblem", "iter_problems", "load_problems"]

DATA = Path(__file__).resolve().parents[1] / "tests" / "data" / "vamp_panda"
ARCHIVE = DATA / "problems.tar.bz2"
PANDA_URDF = DATA / "panda.urdf"
PANDA_SPHERIZED_URDF = DATA / "panda_spherized.urdf"
PANDA_SRDF = DATA / "panda.srdf"
#: the planning group ``panda_arm``'s joints, the order of ``start`` and ``goal``
PANDA_JOINTS = tuple(f"panda_joint{i}" for i in range(1, 8))
_NAME = re.compile(r"^problems/(?P<family>.+)_panda/(?P<kind>scene|request)(?P<index>\d+)\.yaml$")
try:
    _LOADER = yaml.CSafeLoader
except AttributeError:  # PyYAML without libyaml
    _LOADER = yaml.SafeLoader


@dataclass(frozen=True)
class MotionProblem:
    """One problem: ``family`` (e.g. ``"cage"``), ``index`` (1-100), ``scene`` (obstacles and allowed
    pairs), ``start`` and ``goal`` (joint values in ``joint_names`` order, radians), ``start_state`` (every
    joint the request's start state names, fingers included) and ``name`` (``family/index``)."""

    family: str
    index: int
    scene: Scene
    start: tuple[float, ...]
    goal: tuple[float, ...]
    joint_names: tuple[str, ...]
    start_state: dict

    @property
    def name(self) -> str:
        return f"{self.family}/{self.index:04d}"


def iter_problems(archive=ARCHIVE, joint_names=PANDA_JOINTS, families=None,
                  indices=None) -> Iterator[MotionProblem]:
    """Every problem of ``archive`` (families sorted, then by index), or of the ``families`` and problem
    numbers ``indices`` (1-100) named only.
    A scene without its request (or the converse), a request whose start or goal misses one of
    ``joint_names``, or a file name of another form is a ``ValueError`` naming the member."""
    joint_names = tuple(joint_names)
    texts: dict[tuple[str, int], dict[str, tuple[str, bytes]]] = {}
    with tarfile.open(archive, "r:bz2") as tar:  # one pass in archive order (a bz2 stream cannot seek back)
        for m in tar:
            if not m.isfile():
                continue
            hit = _NAME.match(m.name)
            if hit is None:
                raise ValueError(f"{archive}: unexpected member {m.name!r}")
            if (families is not None and hit["family"] not in families) or (
                    indices is not None and int(hit["index"]) not in indices):
                continue
            f = tar.extractfile(m)
            if f is None:
                raise ValueError(f"{archive}: cannot read {m.name}")
            texts.setdefault((hit["family"], int(hit["index"])), {})[hit["kind"]] = (m.name, f.read())
    for (family, index), pair in sorted(texts.items()):
        if set(pair) != {"scene", "request"}:
            raise ValueError(f"{archive}: {family} problem {index} has only a {', '.join(pair)} file")
        (scene_name, scene_text), (request_name, request_text) = pair["scene"], pair["request"]
        scene = scene_from_data(f"{archive}:{scene_name}", yaml.load(scene_text, Loader=_LOADER))
        start_state, goal = _request(yaml.load(request_text, Loader=_LOADER), f"{archive}:{request_name}")
        missing = [j for j in joint_names if j not in start_state or j not in goal]
        if missing:
            raise ValueError(f"{archive}:{request_name}: no start or goal value for {missing}")
        yield MotionProblem(family, index, scene, tuple(start_state[j] for j in joint_names),
                            tuple(goal[j] for j in joint_names), joint_names, start_state)


def load_problems(archive=ARCHIVE, joint_names=PANDA_JOINTS, families=None,
                  indices=None) -> list[MotionProblem]:
    """:func:`iter_problems` as a list."""
    return list(iter_problems(archive, joint_names, families, indices))


def _request(data, where: str) -> tuple[dict, dict]:
    """(start joint state, goal joint values) of a MotionPlanRequest: the start state's ``joint_state``
    and the first goal constraint's ``joint_constraints`` (MBM requests have exactly one)."""
    try:
        js = data["start_state"]["joint_state"]
        start = {str(n): float(v) for n, v in zip(js["name"], js["position"], strict=True)}
        goals = data["goal_constraints"]
        if len(goals) != 1:
            raise ValueError(f"{where}: expected one goal constraint, got {len(goals)}")
        goal = {str(c["joint_name"]): float(c["position"]) for c in goals[0]["joint_constraints"]}
    except (KeyError, TypeError) as exc:
        raise ValueError(f"{where}: not a joint-space MotionPlanRequest ({exc!r})") from None
    return start, goal

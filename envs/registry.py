"""The one table of diffkin's Gymnasium environments: env ID → single-env class, batched task, settings.

``envs/__init__.py`` registers every ID of :data:`ENVS` with Gymnasium (entry point: the env class) and
:func:`diffkin.envs.vector.make_task` builds the batched task of an ID from the same row, so the single and
the batched env of an ID cannot drift apart.
"""

from __future__ import annotations

from dataclasses import dataclass

from .core import Task, TaskEnv
from .imitate import ImitateConfig, ImitateEnv, ImitateTask
from .reach import ReachConfig, ReachEnv, ReachTask
from .track import TrackConfig, TrackEnv, TrackTask

__all__ = ["EnvSpec", "ENVS", "ENV_IDS"]


@dataclass(frozen=True)
class EnvSpec:
    """One environment: its single-env class (the Gymnasium entry point), its batched task and the task's
    settings dataclass (the keyword arguments both accept besides the robot's)."""

    env: type[TaskEnv]
    task: type[Task]
    config: type

    @property
    def entry_point(self) -> str:
        """``"module:Class"`` of the single env, as Gymnasium's registry records it."""
        return f"{self.env.__module__}:{self.env.__name__}"


ENVS: dict[str, EnvSpec] = {
    "diffkin/Reach-v0": EnvSpec(ReachEnv, ReachTask, ReachConfig),
    "diffkin/Track-v0": EnvSpec(TrackEnv, TrackTask, TrackConfig),
    "diffkin/Imitate-v0": EnvSpec(ImitateEnv, ImitateTask, ImitateConfig),
}

#: env ID → Gymnasium entry point, for every environment of :data:`ENVS`
ENV_IDS: dict[str, str] = {env_id: spec.entry_point for env_id, spec in ENVS.items()}

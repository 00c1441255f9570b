"""Gymnasium environments on the diffkin kernels. Importing this package registers the IDs below.

``diffkin/Reach-v0`` (goal-conditioned, HER-ready) and ``diffkin/Track-v0`` (path tracking), both listed
in one table (:data:`diffkin.envs.registry.ENVS`); the torch-batched vector env is
:class:`diffkin.envs.vector.TorchVectorEnv`. The environments know no trainer: the stable-baselines3 adapter
is :mod:`diffkin.training.sb3`.
"""

from __future__ import annotations

from gymnasium.envs.registration import register
from gymnasium.envs.registration import registry as _gym_registry

from .reach import ReachEnv as ReachEnv
from .registry import ENV_IDS as ENV_IDS
from .registry import ENVS as ENVS
from .track import TrackEnv as TrackEnv

# Episode length is enforced by the envs themselves (``episode_steps=``; the batched env shares the logic),
# so no TimeLimit is registered. ``gymnasium.make(..., max_episode_steps=k)`` only adds an outer TimeLimit.
for _env_id, _entry in ENV_IDS.items():
    if _env_id not in _gym_registry:
        register(id=_env_id, entry_point=_entry)

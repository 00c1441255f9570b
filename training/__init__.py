"""Training and evaluation of stable-baselines3 agents on the diffkin envs, driven by configs/*.yaml."""

from diffkin.errors import require

for _module in ("gymnasium", "stable_baselines3"):  # one line naming the extra, not a deep import traceback
    require(_module, "rl", "diffkin.training")

"""Training and evaluation of stable-baselines3 agents on the diffkin envs, driven by configs/*.yaml."""

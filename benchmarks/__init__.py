"""Benchmarks: speed (and memory) of diffkin against pytorch-kinematics, in one run. See benchmarks/run.py."""

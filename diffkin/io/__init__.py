"""Input and output of joint data and files.

- :mod:`diffkin.io.data`: joint vectors, poses and measurements from ``.npy`` / ``.npz`` / ``.csv`` files,
  chunked and memory-mapped;
- :mod:`diffkin.io.streaming`: batch FK / IK over inputs of any size, chunk by chunk;
- :mod:`diffkin.io.distributed`: the same sharded over ``torchrun`` processes, manifests and merges.

Nothing below the models imports this package.
"""

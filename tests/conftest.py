"""Shared test configuration.

The tests run many small tensor operations; on a 2-core CI machine intra-op threading only adds overhead
(and makes small batched linear algebra up to 10x slower when another process holds a core), so the suite
runs torch single-threaded. Speed is measured in benchmarks/, never here.
"""

import os

import torch

torch.set_num_threads(1)
os.environ.setdefault("MPLBACKEND", "Agg")

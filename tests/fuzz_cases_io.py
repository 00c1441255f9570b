"""Fuzz cases of the modules added after the tensor sweep was written: streaming (FK/IK of arrays chunk by
chunk), the shared input rule itself (``validation.tensors``), and the exemptions of the file, URDF and
sharding APIs, whose bad inputs (paths, text, options) are swept in ``tests/test_fuzz_boundary.py``
(see ``tests/fuzzing.py`` for the format)."""

from __future__ import annotations

import torch

from diffkin.io import streaming
from diffkin.io.data import DataFileError
from diffkin.validation import tensors
from tests.fuzz_cases_robots import joints, poses, ur5
from tests.fuzzing import Arg, Case, call_dtype, transform, uniform

#: modules whose every public callable must have a case or an exemption
MODULES: list[str] = [
    "diffkin.io.streaming",
    "diffkin.validation",
    "diffkin.io.data",
    "diffkin.models.urdf_xml",
    "diffkin.io.distributed",
]


def _stream_fk(chain, q):
    res = streaming.stream_fk(chain, q, chunk_size=2)  # several chunks for the 3-row batch
    assert res.count == q.shape[0]
    return torch.tensor([float(res.count)])


def _stream_ik(chain, T):
    res = streaming.stream_ik(chain, T, chunk_size=2, num_seeds=2, seed=0)
    assert res.count == T.shape[0] and 0 <= res.successes <= res.count
    return torch.tensor([float(res.count), *res.position_error])


# A streamed source follows the data-file rule of diffkin.io.data, not the tensor rule: numbers of any real
# dtype are converted to the chain's (as a file's are), bool/complex raise DataFileError, and an empty input
# is a DataFileError (nothing to stream); so the dtype and mixed mutations do not apply (a bfloat16 tensor
# source is widened like a file's numbers: tests/test_fuzz_boundary.py checks it).
_STREAM = {"out_batch": None, "chain": ur5, "empty_raises": DataFileError, "skip": ("dtype", "mixed")}
CASES: list[Case] = [
    Case("streaming.stream_fk", _stream_fk, {"q": Arg(joints(ur5), (6,))}, covers=streaming.stream_fk,
         **_STREAM),
    Case("streaming.stream_ik", _stream_ik, {"T": Arg(poses(ur5), (4, 4))}, covers=streaming.stream_ik,
         **_STREAM),
    Case("validation.tensors", lambda x, T: tensors(("x", x, (3,)), ("T", T, (4, 4))),
         {"x": Arg(uniform(3), (3,)), "T": Arg(transform, (4, 4))}, covers=tensors),
    Case("validation.tensors[like]", lambda x: tensors(("x", x, (3,)), like=ur5(call_dtype())),
         {"x": Arg(uniform(3), (3,))}, follows_chain=True, covers=tensors),
]

_FILES = "takes paths, text or options (no tensor input): swept in tests/test_fuzz_boundary.py"
_PIECE = ("a piece of the input rule that validation.tensors assembles (fuzzed as validation.tensors); "
          "each is unit-tested in tests/test_geometry_validation.py / test_boundary_errors.py")
_RANKS = "process-group plumbing under torchrun (ranks, files, barriers): tests/test_distributed.py"
_RESULT = "a result container (dataclass) without input of its own"
#: public callables without a case, with the reason
EXEMPT: dict[str, str] = {
    "diffkin.io.streaming.FKStreamResult": _RESULT,
    "diffkin.io.streaming.IKStreamResult": _RESULT,
    "diffkin.io.streaming.combine_ik": "combines IKStreamResults (plain numbers), no tensor input",
    "diffkin.io.streaming.seed_of_chunk": "two integers (numpy's SeedSequence refuses negative ones), no "
    "tensor input",
    **{f"diffkin.validation.{name}": _PIECE for name in (
        "as_tensor", "broadcast_batch", "check_broadcasts_to", "check_count", "check_device",
        "check_fits_dtype", "check_dtype", "check_given", "check_lower_bound", "check_number", "check_finite",
        "check_shape",
        "check_tensor", "check_trailing", "common_dtype_device", "shape_str")},
    **{f"diffkin.validation.{name}": "a tensor option's bound (the rule velocity_step, solve_velocity and "
       "the IK tasks share; fuzzed through them), unit-tested in tests/test_boundary_errors.py"
       for name in ("check_nonnegative", "check_positive")},
    **{f"diffkin.models.urdf_xml.{name}": "reads the joint kinds table (a type name in, no tensor input), "
       "unit-tested in tests/test_joint_kinds.py" for name in ("joint_types", "moves")},
    "diffkin.validation.check_end_links": "takes names (no tensor input): the loaders' end-link rule, "
    "unit-tested in tests/test_mjcf.py and tests/test_urdf_models.py",
    **{f"diffkin.io.data.{name}": _FILES for name in (
        "ArraySource", "PoseSource", "RandomJoints", "check_output_path", "open_joint_source",
        "open_pose_source", "open_writer", "read_array", "read_joints", "read_poses", "write_arrays",
        "read_manifest", "DataFileError", "joint_count", "read_measurements", "Writer")},
    **{f"diffkin.models.urdf_xml.{name}": _FILES for name in ("JointSpec", "URDFTree", "InertialSpec",
                                                              "parse_inertials", "parse_urdf", "write_urdf",
                                                              "CollisionSpec", "parse_collisions")},
    **{f"diffkin.io.distributed.{name}": _RANKS for name in (
        "RankInfo", "rank_info", "init", "shard_rows", "part_path", "manifest_path", "write_manifest",
        "read_manifest", "merge_parts", "gather", "agree", "barrier", "finish", "run_sharded")},
}

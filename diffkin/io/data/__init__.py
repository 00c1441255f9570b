"""Reading and writing batches of joint vectors and poses (``.npy``, ``.npz``, ``.csv``), in one piece or
in chunks of bounded memory.

Joint vectors ``(N, n)``
    ``.npy`` array; ``.npz`` key ``q``; ``.csv`` with ``n`` columns, or with a header row that names them
    ``q1 .. qn`` (other columns, such as ``diffkin fk``'s ``x y z qw qx qy qz``, are then ignored). The
    joint count is the file's (its header's run q1, q2, ..., or its shape): a file of another count than the
    robot's is refused with both counts, never cut to fit.

Poses
    ``.npy``: ``(N, 4, 4)`` homogeneous transforms (``(N, K, 4, 4)`` for K end links), ``(N, 3)`` positions
    or ``(N, 7)`` rows ``x y z qw qx qy qz`` (quaternion scalar first).
    ``.npz``: key ``T``, or ``position`` ``(N, 3)`` and optionally ``quaternion`` ``(N, 4)``.
    ``.csv`` with a header row: columns ``x, y, z`` and, for full poses, ``qw, qx, qy, qz`` (other columns
    ignored, so ``diffkin fk``'s CSV is read as it is); only ``x, y, z`` means position-only targets. For K
    end links the names carry the end's number: ``x_1 .. qz_K``.
    Headerless ``.csv``: 3 columns are ``x y z``, 7 columns ``x y z qw qx qy qz``; any other width is refused.

**Quaternion rule.** A quaternion whose norm differs from 1 by more than ``QUATERNION_NORM_TOLERANCE``
(1e-3) is refused with a :class:`DataFileError` naming its row; it is never normalised silently (a
7-column file of joint vectors is therefore refused by ``diffkin ik``, not read as poses). Within the
tolerance it is normalised. A 4x4 pose must be rigid by the one rule of
:data:`diffkin.transforms.RIGIDITY_TOLERANCE` (max |RᵀR − I|, |det R − 1| and the bottom row's deviation at
most 1e-3): within it the pose is re-orthonormalised, beyond it refused naming the file and row.

Streaming: :func:`open_joint_source` / :func:`open_pose_source` return sources read chunk by chunk
(``.npy`` through a memory map, ``.npz`` member by member from the zip stream, ``.csv`` line by line), and
:func:`open_writer` writes ``.npy`` / ``.csv`` / ``.npz`` outputs chunk by chunk (an ``.npz`` is assembled
from streamed ``.npy`` parts at the end). Outputs are written to ``<name>.part`` and renamed when complete.
"""


from .formats import (
    MANIFEST_FORMAT,
    MANIFEST_SUFFIX,
    QUATERNION_NORM_TOLERANCE,
    DataFileError,
    check_output_path,
    read_array,
    read_manifest,
)
from .joints import RandomJoints, joint_count, open_joint_source, read_joints
from .poses import PoseSource, open_pose_source, read_measurements, read_poses
from .sources import ArraySource
from .writers import Writer, open_writer, write_arrays

__all__ = [
    "DataFileError",
    "QUATERNION_NORM_TOLERANCE",
    "ArraySource",
    "PoseSource",
    "RandomJoints",
    "check_output_path",
    "open_joint_source",
    "open_pose_source",
    "open_writer",
    "read_array",
    "joint_count",
    "read_joints",
    "read_measurements",
    "read_poses",
    "write_arrays",
    "Writer",
    "read_manifest",
    "MANIFEST_SUFFIX",
    "MANIFEST_FORMAT",
]

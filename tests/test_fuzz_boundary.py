"""Fuzz sweep of the public callables that take files, text, names and options rather than tensors (models,
URDF/YAML readers, data files, run configs, envs, the CLI), and of the tensor callables added since the
tensor sweep (``tests/test_fuzz.py``) was written (streaming, the shared ``validation.tensors`` rule): every
bad input gives one of diffkin's typed errors (``diffkin.errors.DiffkinError`` subclasses) naming it —
no raw exception, no silent result, no hang (the suite's hang guard, pyproject's pytest ``timeout``)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from diffkin import errors, ik, models
from diffkin.io.data import read_array, read_joints, read_poses
from diffkin.io.streaming import stream_fk, stream_ik
from diffkin.models.io import read_yaml
from diffkin.models.urdf_xml import parse_urdf
from diffkin.validation import tensors

F64 = torch.float64
URDF_OK = ('<robot name="r"><link name="a"/><link name="b"/><joint name="j" type="revolute">'
           '<parent link="a"/><child link="b"/><axis xyz="0 0 1"/><limit lower="-1" upper="1"/>'
           '</joint></robot>')
NAN_ORIGIN = URDF_OK.replace("<axis", '<origin xyz="nan 0 0"/><axis')
#: raw crashes found by this sweep in files another engineer is rewriting (diffkin/chain.py, models/urdf.py):
#: recorded here so the sweep stays a check; a fixed one fails the test until it is removed from the list
KNOWN_OUTSIDE: dict[str, str] = {}


def _files(tmp_path):
    """Malformed files by name: (suffix, bytes)."""
    specs = {
        "non_utf8": b"name: x\n\xff\xfe: 1\n",
        "empty": b"",
        "binary": bytes(range(256)),
        "yaml_list": b"- 1\n- 2\n",
        "yaml_bad": b"a: [1, 2\nb: : :\n",
        "yaml_scalar": b"42\n",
        "csv_text": b"q1,q2\nfoo,bar\n",
        "csv_ragged": b"1,2,3\n4,5\n",
        "csv_nan": b"1,2,nan,4,5,6\n",
    }
    out = {}
    for name, data in specs.items():
        for suffix in (".yaml", ".urdf", ".csv", ".npy", ".npz"):
            p = tmp_path / f"{name}{suffix}"
            p.write_bytes(data)
            out[f"{name}{suffix}"] = p
    return out


def _calls(tmp_path):
    f = _files(tmp_path)
    missing = tmp_path / "missing.yaml"
    chain = models.load("ur5", dtype=F64)
    T = chain.forward_kinematics(torch.zeros(2, 6, dtype=F64)).detach()
    calls = {}
    for key, path in f.items():
        calls[f"models.load[{key}]"] = lambda p=path: models.load(str(p))
        calls[f"parse_urdf[{key}]"] = lambda p=path: parse_urdf(p)
        calls[f"from_urdf[{key}]"] = lambda p=path: models.from_urdf(p, "b")
        if key.endswith((".csv", ".npy", ".npz")) and not key.startswith(("yaml_scalar", "csv_nan")):
            calls[f"read_array[{key}]"] = lambda p=path: read_array(p)  # (a raw reader: 42 and NaN are data)
        if key.endswith((".csv", ".npy", ".npz")):
            calls[f"read_joints[{key}]"] = lambda p=path: read_joints(p, 6)  # 6 finite columns or an error
            calls[f"read_poses[{key}]"] = lambda p=path: read_poses(p)
            calls[f"stream_fk[{key}]"] = lambda p=path: stream_fk(chain, p)
        if key in ("non_utf8.yaml", "binary.yaml", "yaml_bad.yaml"):  # (any valid YAML is read_yaml's data)
            calls[f"read_yaml[{key}]"] = lambda p=path: read_yaml(p)
    calls.update({
        "models.load[missing]": lambda: models.load(str(missing)),
        "models.load[unknown name]": lambda: models.load("no_such_robot"),
        "models.load[int]": lambda: models.load(3),
        "models.load[None]": lambda: models.load(None),
        "models.load[.urdf]": lambda: models.load("arm.urdf"),
        "models.load[.xml]": lambda: models.load("arm.xml"),
        "models.load[dtype int64]": lambda: models.load("ur5", dtype=torch.int64),
        "models.load[device meta]": lambda: models.load("ur5", device="meta"),
        "models.load[device bogus]": lambda: models.load("ur5", device="bogus"),
        "models.load[device cuda:99]": lambda: models.load("ur5", device="cuda:99"),
        "parse_urdf[empty text]": lambda: parse_urdf("<"),
        "parse_urdf[not robot]": lambda: parse_urdf("<model/>"),
        "parse_urdf[no links]": lambda: parse_urdf("<robot/>"),
        "parse_urdf[bytes]": lambda: parse_urdf(b"\xff\xfe<robot/>"),
        "parse_urdf[int]": lambda: parse_urdf(5),
        "parse_urdf[missing path]": lambda: parse_urdf(str(tmp_path / "none.urdf")),
        "parse_urdf[nan origin]": lambda: parse_urdf(NAN_ORIGIN),
        "parse_urdf[zero axis]": lambda: parse_urdf(URDF_OK.replace('0 0 1', '0 0 0')),
        "parse_urdf[bad limit]": lambda: parse_urdf(URDF_OK.replace('lower="-1"', 'lower="2"')),
        "from_urdf[unknown end]": lambda: models.from_urdf(URDF_OK, "zz"),
        "from_urdf[no end]": lambda: models.from_urdf(URDF_OK, []),
        "from_urdf[int end]": lambda: models.from_urdf(URDF_OK, 3),
        "read_yaml[text list]": lambda: read_yaml("- a\n- b: [\n"),
        "read_array[missing]": lambda: read_array(tmp_path / "none.npy"),
        "read_array[bad suffix]": lambda: read_array(f["empty.yaml"]),
        "read_joints[wrong n]": lambda: read_joints(_npy(tmp_path, np.zeros((3, 4))), 6),
        "read_joints[n=0]": lambda: read_joints(_npy(tmp_path, np.zeros((3, 6))), 0),
        "read_poses[bad shape]": lambda: read_poses(_npy(tmp_path, np.zeros((3, 5)))),
        "read_poses[object npy]": lambda: read_poses(_npy(tmp_path, np.array([None, 1], dtype=object))),
        "stream_fk[wrong n]": lambda: stream_fk(chain, np.zeros((3, 4))),
        "stream_fk[chunk 0]": lambda: stream_fk(chain, np.zeros((3, 6)), chunk_size=0),
        "stream_fk[bad output]": lambda: stream_fk(chain, np.zeros((3, 6)), tmp_path / "out.txt"),
        "stream_ik[bad shape]": lambda: stream_ik(chain, np.zeros((3, 5))),
        "stream_ik[nan]": lambda: stream_ik(chain, np.full((3, 3), np.nan)),
        "stream_ik[start > stop]": lambda: stream_ik(chain, T[..., :3, 3].numpy(), start=2, stop=1),
        "ik.solve[num_seeds 0]": lambda: ik.solve(chain, T, num_seeds=0),
        "ik.solve[num_seeds -1]": lambda: ik.solve(chain, T, num_seeds=-1),
        "ik.solve[num_seeds 1.5]": lambda: ik.solve(chain, T, num_seeds=1.5),
        "ik.solve[num_seeds True]": lambda: ik.solve(chain, T, num_seeds=True),
        "ik.solve[max_iterations 0]": lambda: ik.solve(chain, T, max_iterations=0),
        "ik.solve[tolerance -1]": lambda: ik.solve(chain, T, position_tolerance=-1.0),
        "ik.solve[tolerance nan]": lambda: ik.solve(chain, T, orientation_tolerance=math.nan),
        "ik.solve[damping -1]": lambda: ik.solve(chain, T, damping=-1.0),
        "ik.solve[q0 wrong n]": lambda: ik.solve(chain, T, torch.zeros(5, dtype=F64)),
        "ik.solve[T not rigid]": lambda: ik.solve(chain, T * 2),
        "ik.solve[T None]": lambda: ik.solve(chain, None),
        "ik.solve[T str]": lambda: ik.solve(chain, "pose"),
        "tensors[str]": lambda: tensors(("x", "abc", (3,))),
        "tensors[ragged]": lambda: tensors(("x", [[1.0, 2.0], [3.0]], None)),
        "tensors[object]": lambda: tensors(("x", np.array([None, 1.0], dtype=object), None)),
        "tensors[dict]": lambda: tensors(("x", {"a": 1.0}, None)),
        "chain.forward_kinematics[None]": lambda: chain.forward_kinematics(None),
        "chain.forward_kinematics[str]": lambda: chain.forward_kinematics("q"),
    })
    return calls


def _npy(tmp_path, arr) -> str:
    p = tmp_path / f"a{abs(hash(arr.tobytes() if arr.dtype != object else 'o')) % 10**8}.npy"
    np.save(p, arr, allow_pickle=True)
    return str(p)


def test_every_bad_file_text_or_option_is_a_typed_error(tmp_path):
    silent, raw = [], []
    for name, call in _calls(tmp_path).items():
        try:
            out = call()
        except errors.DiffkinError as exc:
            assert str(exc).strip(), f"{name}: an empty message"
            continue
        except Exception as exc:  # noqa: BLE001 - classifying every failure is the point
            raw.append(f"{name}: {type(exc).__name__}: {str(exc)[:120]}")
            continue
        silent.append(f"{name}: returned {type(out).__name__}")
    known = [r for r in raw if r.split(":")[0] in KNOWN_OUTSIDE]
    raw = [r for r in raw if r not in known]
    fixed = set(KNOWN_OUTSIDE) - {r.split(":")[0] for r in known}
    assert not fixed, f"fixed meanwhile, remove from KNOWN_OUTSIDE: {sorted(fixed)}"
    assert not raw, "raw crashes:\n" + "\n".join(raw)
    assert not silent, "no error for bad input:\n" + "\n".join(silent)


def _env_calls():
    from diffkin.envs.vector import TorchVectorEnv

    def stepped(action):
        env = TorchVectorEnv("diffkin/Reach-v0", 2)
        env.reset(seed=0)
        return env.step(action)

    return {
        "TorchVectorEnv[unknown id]": lambda: TorchVectorEnv("diffkin/Nope-v0", 2),
        "TorchVectorEnv[num_envs 0]": lambda: TorchVectorEnv("diffkin/Reach-v0", 0),
        "TorchVectorEnv[num_envs 1.5]": lambda: TorchVectorEnv("diffkin/Reach-v0", 1.5),
        "TorchVectorEnv[device meta]": lambda: TorchVectorEnv("diffkin/Reach-v0", 2, device="meta"),
        "TorchVectorEnv[device bogus]": lambda: TorchVectorEnv("diffkin/Reach-v0", 2, device="bogus"),
        "step[None]": lambda: stepped(None),
        "step[str]": lambda: stepped("left"),
        "step[wrong shape]": lambda: stepped(torch.zeros(3, 7)),
        "step[nan]": lambda: stepped(torch.full((2, 7), math.nan)),
        "step[int64]": lambda: stepped(torch.zeros(2, 7, dtype=torch.int64)),
        "step[object]": lambda: stepped(np.array([[None] * 7] * 2, dtype=object)),
    }


def test_every_bad_env_call_is_a_typed_error():
    import gymnasium

    from diffkin.envs.vector import TorchVectorEnv

    raw, silent = [], []
    for name, call in _env_calls().items():
        try:
            call()
        except errors.DiffkinError:
            continue
        except Exception as exc:  # noqa: BLE001
            raw.append(f"{name}: {type(exc).__name__}: {str(exc)[:120]}")
            continue
        silent.append(name)
    assert not raw, "raw crashes:\n" + "\n".join(raw)
    assert not silent, f"no error for: {silent}"
    with pytest.raises(gymnasium.error.ResetNeeded, match="reset"):  # a usage error: Gymnasium's typed one
        TorchVectorEnv("diffkin/Reach-v0", 2).step(torch.zeros(2, 7))


@pytest.mark.parametrize("argv", [
    ["fk", "--robot", "no_such_robot", "--random", "3"],
    ["fk", "--robot", "ur5.urdf", "--random", "3"],
    ["fk", "--robot", "ur5", "--input", "MISSING.npy"],
    ["ik", "--robot", "ur5", "--random", "0"],
    ["ik", "--robot", "ur5", "--random", "2", "--num-seeds", "0"],
    ["ik", "--robot", "ur5", "--random", "2", "--position-tolerance", "nan"],
    ["train", "--config", "MISSING.yaml"],
    ["train", "--config", "BAD.yaml"],
    ["models", "show", "no_such_robot"],
    ["evaluate", "MISSING_RUN"],
    ["trajectory", "joint", "--start", "0", "1", "--end", "1", "--output", "t.npz"],
])
def test_cli_bad_input_is_one_error_line(argv, tmp_path, capsys):
    from diffkin.cli import main

    (tmp_path / "BAD.yaml").write_text("a: [1, 2\nb: : :\n")
    argv = [str(tmp_path / a) if a.isupper() or a == "t.npz" else a for a in argv]
    capsys.readouterr()
    rc = main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2, err
    last = [ln for ln in err if ln.startswith("error:")]
    assert len(last) == 1 and "internal error" not in last[0], err

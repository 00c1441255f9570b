"""Robots by name (issue 40 item 8): every shipped URDF and MuJoCo robot loads from the installed package
by name, ``models.available(details=True)`` lists them with their source and licence, and a
``robot_descriptions`` name loads through that package (offline, from a local cache laid out as
``robot_descriptions`` expects)."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from diffkin import models
from diffkin.errors import ModelError
from diffkin.models import catalog

ROBOTS = catalog.ROBOTS_DIR
CATALOG = json.loads((ROBOTS / "catalog.json").read_text())["robots"]
F64 = torch.float64
mujoco = pytest.importorskip("mujoco")


def _readme_row(entry) -> str:
    """The README line that records a shipped file (the MJCF table's row, the URDF list's item)."""
    file = entry["file"].split("/", 1)[1]
    readme = (ROBOTS / entry["file"].split("/")[0] / "README.md")
    if not readme.is_file():  # the two files written for diffkin (models/data) carry their header instead
        return Path(ROBOTS / entry["file"]).read_text()[:600]
    text = readme.read_text()
    key = f"`{file}`"
    rows = [line for line in text.splitlines() if key in line or f"`{Path(file).name}`" in line]
    assert rows, f"{readme.name} does not record {file}"
    return "\n".join(rows)


@pytest.mark.parametrize("entry", CATALOG, ids=[e["name"] for e in CATALOG])
def test_every_shipped_robot_loads_by_name_and_aliases(entry):
    """The name and each alias give the same chain: the catalogue's file, its default end links in order;
    FK at a random configuration equals the file read directly; the licence agrees with the README."""
    path = (ROBOTS / entry["file"]).resolve()
    assert path.is_file() and str(path).startswith(str(Path(models.__file__).parent))  # inside the package
    chain = models.load(entry["name"], dtype=F64)
    assert chain.n_ends == len(entry["end_links"])
    info = models.info(entry["name"])
    assert info.path == path and info.end_links == tuple(entry["end_links"]) and info.source and info.licence
    reader = models.from_mjcf if entry["format"] == "mjcf" else models.from_urdf
    extra = {"floating_base": True} if entry.get("floating_base") else {}
    ends = entry["end_links"][0] if len(entry["end_links"]) == 1 else entry["end_links"]  # one: (..., 4, 4)
    direct = reader(path, ends, dtype=F64, **extra)
    q = direct.random_configuration((3,), generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(chain.forward_kinematics(q), direct.forward_kinematics(q), rtol=0, atol=0)
    for alias in entry["aliases"]:
        assert models.info(alias) == info
    licence = entry["licence"]
    row = _readme_row(entry)
    words = {"Apache-2.0": ("Apache-2.0",), "BSD-3-Clause": ("BSD-3-Clause",),
             "BSD-2-Clause": ("BSD 2-clause", "BSD (2 clauses)"), "MIT": ("MIT",),
             "CC-BY-NC-ND-3.0": ("CC BY-NC-ND 3.0",), "not stated in the file": ("no licence",),
             "MIT (diffkin)": ("written for diffkin",)}
    for part in licence.split(" AND "):
        assert any(w in row for w in words[part]), f"{entry['name']}: licence {part!r}, the README: {row!r}"


def test_available_lists_every_name_once_with_details():
    names = models.available()
    assert names == sorted(set(names))
    shipped = {e["name"] for e in CATALOG}
    dh = {p.stem for p in models.DATA_DIR.glob("*.yaml")}
    assert set(names) == shipped | dh and not shipped & dh
    details = models.available(details=True)
    assert [r.name for r in details] == names
    assert {r.format for r in details} == {"dh", "urdf", "mjcf"}
    assert all(r.source and r.licence for r in details)
    # every Menagerie model of the MJCF index and every URDF file ships under a name
    index = json.loads((ROBOTS / "mjcf" / "index.json").read_text())
    files = {e["file"] for e in CATALOG}
    assert {f"mjcf/{e['file']}" for e in index} <= files
    assert {f"urdf/{p.name}" for p in (ROBOTS / "urdf").glob("*.urdf")} <= files


def test_end_link_replaces_the_defaults_and_errors_name_the_robot():
    ur = models.load("ur10e", dtype=F64, end_link="wrist_2_link")
    assert ur.n_ends == 1 and ur.nq == 5
    with pytest.raises(ModelError, match="unknown model 'ur11'.*ur10e"):
        models.load("ur11")
    with pytest.raises(ModelError, match="panda: end_link"):
        models.load("panda", end_link="panda_link8")  # a DH model ends where its table ends
    assert type(models.load("panda")).__name__ == "DHChain"  # the DH name keeps its meaning


def test_the_cli_takes_the_same_names(capsys):
    from diffkin.cli import main

    assert main(["fk", "--robot", "g1", "--random", "3", "--dtype", "float64"]) == 0
    assert "FK of 3 configurations of 'g1_29dof_rev_1_0'" in capsys.readouterr().out
    assert main(["models", "show", "yumi"]) == 0
    out = capsys.readouterr().out
    assert "yumi.urdf" in out and "gripper_l_base" in out


def _menagerie_cache(tmp_path: Path) -> tuple[Path, str]:
    """A local ``robot_descriptions`` cache holding the one Menagerie file the test reads, as a git commit:
    ``<cache>/mujoco_menagerie-<sha>/mujoco_menagerie`` is where ``clone_to_cache`` looks for commit <sha>."""
    git = ["git", "-c", "user.name=t", "-c", "user.email=t@t", "-c", "commit.gpgsign=false"]
    work = tmp_path / "work"
    (work / "universal_robots_ur10e").mkdir(parents=True)
    src = ROBOTS / "mjcf" / "universal_robots_ur10e" / "ur10e.xml"
    (work / "universal_robots_ur10e" / "ur10e.xml").write_bytes(src.read_bytes())
    subprocess.run([*git, "init", "-q", str(work)], check=True)
    subprocess.run([*git, "-C", str(work), "add", "."], check=True)
    subprocess.run([*git, "-C", str(work), "commit", "-q", "-m", "ur10e"], check=True)
    sha = subprocess.run(["git", "-C", str(work), "rev-parse", "HEAD"], check=True, capture_output=True,
                         text=True).stdout.strip()
    target = tmp_path / "cache" / f"mujoco_menagerie-{sha}" / "mujoco_menagerie"
    target.parent.mkdir(parents=True)
    work.rename(target)
    return tmp_path / "cache", sha


def test_a_robot_descriptions_name_loads_offline_from_its_cache(tmp_path):
    """``models.load("ur10e_mj_description", end_link=...)`` through the installed ``robot_descriptions``, in
    a fresh interpreter (its modules clone on import) with a cache that needs no network."""
    pytest.importorskip("robot_descriptions")
    cache, sha = _menagerie_cache(tmp_path)
    code = (
        "import torch\nfrom diffkin import models\nfrom diffkin.errors import ModelError\n"
        "a = models.load('ur10e_mj_description', dtype=torch.float64, end_link='wrist_3_link')\n"
        "b = models.load('ur10e', dtype=torch.float64)\n"
        "q = b.random_configuration((4,), generator=torch.Generator().manual_seed(1))\n"
        "assert torch.equal(a.forward_kinematics(q), b.forward_kinematics(q))\n"
        "info = models.info('ur10e_mj_description')\n"
        "assert info.format == 'mjcf' and info.path.name == 'ur10e.xml', info\n"
        "try:\n    models.load('ur10e_mj_description')\nexcept ModelError as e:\n"
        "    assert 'end_link' in str(e)\nelse:\n    raise SystemExit('no end_link: not refused')\n"
        "print('ok')\n"
    )
    env = {**os.environ, "ROBOT_DESCRIPTIONS_CACHE": str(cache), "ROBOT_DESCRIPTION_COMMIT": sha,
           "GIT_TERMINAL_PROMPT": "0"}
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert proc.returncode == 0 and proc.stdout.strip().endswith("ok"), proc.stderr[-3000:]


def test_without_robot_descriptions_its_names_are_unknown(monkeypatch):
    monkeypatch.setitem(sys.modules, "robot_descriptions", None)  # import fails as when not installed
    monkeypatch.setitem(sys.modules, "robot_descriptions._descriptions", None)
    with pytest.raises(ModelError, match="unknown model 'ur10e_mj_description'.*robot_descriptions"):
        models.load("ur10e_mj_description", end_link="wrist_3_link")


def test_a_robot_the_wheel_does_not_carry_is_named_with_its_licence(monkeypatch, tmp_path):
    """In an installed package the files whose licence keeps them out of the wheel are absent: the name is
    not listed, and loading it says why (here the file is moved away to stand for the installed case)."""
    import dataclasses

    table = dict(catalog._shipped())
    gone = dataclasses.replace(table["talos_reduced"], path=tmp_path / "talos_reduced.urdf")
    table["talos_reduced"] = gone
    monkeypatch.setattr(catalog, "_shipped", lambda: table)
    assert not gone.wheel and "talos_reduced" not in models.available()
    with pytest.raises(ModelError, match="talos_reduced: its URDF file is not in the installed.*CC-BY-NC"):
        models.load("talos_reduced")
    assert {e["name"] for e in CATALOG if not e["wheel"]} >= {"talos_reduced", "tiago_dual", "yumi"}
    assert all(e["wheel"] for e in CATALOG if e["name"] in ("unitree_g1_29dof", "universal_robots_ur10e"))

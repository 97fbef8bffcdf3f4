"""Demo libraries in the original HDF5 layout: round trip, foreign files, refusals."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest

from knotlab.app.cli import main
from knotlab.core.agent import Agent
from knotlab.core.demos.library import DemoLibrary
from knotlab.core.errors import CorruptFileError, InvalidInputError
from knotlab.core.interop.h5_demos import export_library_h5, import_library_h5
from knotlab.core.tasks import get_task

SHIPPED = get_task("overhand").files.library_path


@pytest.fixture(scope="module")
def shipped() -> DemoLibrary:
    return DemoLibrary.load(SHIPPED)


@pytest.fixture(scope="module")
def exported(shipped: DemoLibrary, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return export_library_h5(shipped, tmp_path_factory.mktemp("h5") / "demos.h5")


def _foreign(exported: Path, out: Path, *, nodes: bool = False, groups: int | None = None) -> Path:
    """The export without knotlab's additions: what a lab's own recording looks like."""
    shutil.copy(exported, out)
    with h5py.File(out, "a") as f:
        for k in list(f.attrs):
            del f.attrs[k]
        for i, g in enumerate(sorted(f)):
            if groups is not None and i >= groups:
                del f[g]
                continue
            del f[g]["knotlab"], f[g]["stamps"]
            if not nodes:
                del f[g]["rope_nodes"]
    return out


def test_export_then_import_gives_the_same_content_hash(tmp_path, capsys):
    out_h5, out_npz = tmp_path / "lib.h5", tmp_path / "lib.npz"
    assert main(["demos", "export", str(SHIPPED), "--out", str(out_h5)]) == 0
    assert main(["demos", "import", str(out_h5), "--out", str(out_npz), "--json"]) == 0
    report = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert report["hash"] == DemoLibrary.load(SHIPPED).content_hash()
    assert report["native"] and report["rope_nodes"]
    with h5py.File(out_h5) as f:  # the original layout, readable without knotlab
        g = f["s000-seg00"]
        assert g["cloud_xyz"].shape[1] == 3
        assert g["l_gripper_tool_frame/hmat"].shape[1:] == (4, 4)
        assert g["r_gripper_joint"].shape == (g["l_gripper_tool_frame/hmat"].shape[0],)
        assert isinstance(g["description"][()], bytes)


def test_a_foreign_file_without_rope_nodes_ranks_with_nn_and_greedy_shape(
    exported, shipped, tmp_path
):
    report = import_library_h5(_foreign(exported, tmp_path / "lab.h5"), observation="centreline")
    lib = report.library
    assert not report.native and not lib.has_rope_nodes
    assert report.timed_from_path == len(lib) == len(shipped)
    assert lib.keys[0] == "s000-seg00"  # a foreign segment keeps its group name
    assert np.array_equal(lib[0].pre_cloud_n3, shipped[0].pre_cloud_n3)
    # registration needs only the clouds: nearest neighbour ranks a demo's own cloud first
    agent = Agent(lib, None, "nn")
    best = agent.rank(lib[7].pre_cloud_n3, 1)[0]
    assert best.demo_key == lib.keys[7] and best.trajectory is not None
    with pytest.raises(InvalidInputError, match="rope states"):
        lib.start_states()  # task sets need them, and say so


def test_rope_nodes_in_a_foreign_file_give_each_segment_the_next_ones_rope(exported, tmp_path):
    lib = import_library_h5(_foreign(exported, tmp_path / "lab.h5", nodes=True, groups=6)).library
    assert lib.has_rope_nodes
    first, second = lib[0], lib[1]
    assert first.start_index == second.start_index and second.step_index == 1
    assert np.array_equal(first.post_nodes_k3, second.pre_nodes_k3)
    assert first.metadata["post_nodes"] == "the next segment's rope_nodes"


def _break(path: Path, edit) -> Path:
    with h5py.File(path, "a") as f:
        edit(f)
    return path


def _set(group: str, key: str, value) -> object:
    def edit(f):
        del f[group][key]
        f[group][key] = value

    return edit


CASES = [
    (
        "missing key",
        lambda f: f["s000-seg00"].__delitem__("cloud_xyz"),
        "s000-seg00/cloud_xyz: missing",
    ),
    (
        "wrong shape",
        _set("s000-seg01", "cloud_xyz", np.zeros((81, 2))),
        "s000-seg01/cloud_xyz: shape (81, 2)",
    ),
    (
        "NaN",
        _set("s000-seg02", "cloud_xyz", np.full((81, 3), np.nan)),
        "s000-seg02/cloud_xyz: contains NaN",
    ),
    (
        "never closes",
        _set("s001-seg00", "r_gripper_joint", np.full(25, 0.08)),
        "s001-seg00/l_gripper_joint, r_gripper_joint: neither gripper ever closes",
    ),
    (
        "not rigid",
        lambda f: f["s001-seg01/l_gripper_tool_frame/hmat"].__setitem__((0, 0, 0), 2.0),
        "s001-seg01/l_gripper_tool_frame/hmat: pose 0 is not a rigid transform",
    ),
    (
        "group name",
        lambda f: f.move("s002-seg00", "demo-two"),
        "demo-two: group name is not <demo>-seg<NN>",
    ),
    (
        "poses disagree",
        _set("s002-seg01", "r_gripper_tool_frame/hmat", np.tile(np.eye(4), (3, 1, 1))),
        "s002-seg01/r_gripper_tool_frame/hmat: 3 poses",
    ),
]


@pytest.mark.parametrize("what,edit,message", CASES, ids=[c[0] for c in CASES])
def test_a_bad_file_is_refused_naming_group_and_key(exported, tmp_path, what, edit, message):
    path = _break(_foreign(exported, tmp_path / "bad.h5", groups=8), edit)
    if what == "never closes":  # the left gripper must stay open too
        _break(path, _set("s001-seg00", "l_gripper_joint", np.full(25, 0.08)))
    with pytest.raises(CorruptFileError) as err:
        import_library_h5(path)
    assert message in str(err.value)


def test_the_command_refuses_a_bad_file_in_one_line_and_writes_nothing(exported, tmp_path, capsys):
    path = _break(
        _foreign(exported, tmp_path / "bad.h5", groups=4),
        _set("s000-seg00", "cloud_xyz", np.zeros((5, 4))),
    )
    out = tmp_path / "lib.npz"
    assert main(["demos", "import", str(path), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "s000-seg00/cloud_xyz: shape (5, 4)" in err[0]
    assert not out.exists()


def test_export_does_not_overwrite_without_force(tmp_path, capsys):
    out = tmp_path / "lib.h5"
    out.write_bytes(b"mine")
    assert main(["demos", "export", str(SHIPPED), "--out", str(out)]) == 2
    assert "--force" in capsys.readouterr().err and out.read_bytes() == b"mine"

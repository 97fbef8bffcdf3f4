"""Output files appear complete or not at all, and bad output paths are refused up front."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from knotlab.core.atomic import atomic_open, atomic_path, check_output_dir, check_output_file
from knotlab.core.errors import OutputPathError
from knotlab.core.npzfile import read_npz, write_npz


def test_a_failed_write_keeps_the_old_file_and_leaves_no_temporary(tmp_path: Path) -> None:
    path = write_npz(tmp_path / "a.npz", {"x": np.arange(3)}, {"v": 1})
    before = path.read_bytes()
    with pytest.raises(ValueError):  # object arrays need pickles, which knotlab never writes
        write_npz(path, {"x": np.array([{}, []], dtype=object)}, {"v": 2})
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.npz"]
    with pytest.raises(RuntimeError), atomic_open(tmp_path / "b.txt") as fh:
        fh.write("half")
        raise RuntimeError("crash mid-write")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.npz"]


def test_a_finished_write_replaces_the_file_with_normal_permissions(tmp_path: Path) -> None:
    path = tmp_path / "sub" / "c.txt"
    with atomic_open(path) as fh:
        fh.write("new")
    assert path.read_text() == "new" and (path.stat().st_mode & 0o044)  # not a private 0600
    with atomic_path(tmp_path / "d.npz") as tmp:
        assert tmp.parent == tmp_path and tmp.suffix == ".npz" and tmp.name.startswith(".d.")
        write_npz(tmp, {"x": np.ones(2)}, {})
    arrays, _ = read_npz(tmp_path / "d.npz", "test")
    assert np.array_equal(arrays["x"], np.ones(2))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d.npz", "sub"]


@pytest.mark.parametrize(
    ("name", "problem"),
    [
        ("plain.txt/x.npz", "is a file, not a folder"),
        ("plain.txt/deeper/x.npz", "is a file, not a folder"),
        ("folder", "is a folder"),
        ("x.png", "expected a .npz file name"),
    ],
)
def test_bad_output_files_are_refused(tmp_path: Path, name: str, problem: str) -> None:
    (tmp_path / "plain.txt").write_text("x")
    (tmp_path / "folder").mkdir()
    with pytest.raises(OutputPathError, match=problem):
        check_output_file(tmp_path / name)
    assert check_output_file(tmp_path / "new" / "deeper" / "x.NPZ") == tmp_path / "new/deeper/x.NPZ"
    assert not (tmp_path / "new").exists()  # checking creates nothing
    with pytest.raises(OutputPathError, match="is a file; expected a folder"):
        check_output_dir(tmp_path / "plain.txt")
    assert check_output_dir(tmp_path / "folder" / "new") == tmp_path / "folder" / "new"

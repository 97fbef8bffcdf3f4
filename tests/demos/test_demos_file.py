"""DemoLibrary file format: round trip, byte-determinism, and clear errors on bad files."""

from __future__ import annotations

import json
import zipfile

import numpy as np
import pytest

from knotlab.core.demos.library import DemoLibrary, DemoSegment, segment_key
from knotlab.core.errors import CorruptFileError, InvalidInputError
from knotlab.core.npzfile import read_npz, write_npz
from knotlab.core.world.trajectory import GripperTrajectory, down_rotation


def _segment(start: int, step: int, seed: int) -> DemoSegment:
    rng = np.random.default_rng(seed)
    n_t = 3 + step
    rot = np.broadcast_to(down_rotation(), (2, n_t, 3, 3))
    closed = np.zeros((2, n_t), dtype=bool)
    closed[1, 1:-1] = True
    traj = GripperTrajectory(np.arange(n_t) * 0.5, rng.normal(size=(2, n_t, 3)), rot, closed)
    nodes = np.column_stack([np.linspace(-0.5, 0.5, 41), np.zeros(41), np.full(41, 0.01)])
    return DemoSegment(
        key=segment_key(start, step),
        start_index=start,
        step_index=step,
        pre_nodes_k3=nodes + rng.normal(scale=1e-3, size=nodes.shape),
        pre_cloud_n3=rng.normal(size=(60 + step, 3)),
        trajectory=traj,
        post_nodes_k3=nodes,
        metadata={"seed": seed, "style": {"loop_radius": 0.08}},
    )


@pytest.fixture
def library() -> DemoLibrary:
    segs = [_segment(s, t, 10 * s + t) for s in range(3) for t in range(3)]
    return DemoLibrary(segs, {"generator": "test", "seed": 0})


def test_round_trip_preserves_every_array_and_the_hash(tmp_path, library):
    path = library.save(tmp_path / "lib.npz")
    loaded = DemoLibrary.load(path)
    assert loaded.keys == library.keys
    assert loaded.content_hash() == library.content_hash()
    for a, b in zip(library, loaded, strict=True):
        np.testing.assert_array_equal(a.pre_cloud_n3, b.pre_cloud_n3)
        np.testing.assert_array_equal(a.post_nodes_k3, b.post_nodes_k3)
        assert a.trajectory.equals(b.trajectory)
        assert a.metadata == b.metadata
    assert loaded.summary()["segments_per_step"] == {0: 3, 1: 3, 2: 3}
    assert loaded.index_of("s002-t1") == 7


def test_saving_twice_gives_identical_bytes(tmp_path, library):
    a = library.save(tmp_path / "a.npz").read_bytes()
    b = DemoLibrary(list(library), dict(library.metadata)).save(tmp_path / "b.npz").read_bytes()
    assert a == b


def test_truncated_file_error_names_the_file(tmp_path, library):
    raw = library.save(tmp_path / "lib.npz").read_bytes()
    bad = tmp_path / "truncated.npz"
    bad.write_bytes(raw[: len(raw) * 2 // 3])
    with pytest.raises(CorruptFileError, match=r"truncated\.npz"):
        DemoLibrary.load(bad)


def test_altered_array_fails_the_hash_check(tmp_path, library):
    path = library.save(tmp_path / "lib.npz")
    arrays, header = read_npz(path, "demo library")
    arrays["clouds_n3"] = arrays["clouds_n3"] + 1e-9
    write_npz(tmp_path / "altered.npz", arrays, header)
    with pytest.raises(CorruptFileError, match="hash mismatch"):
        DemoLibrary.load(tmp_path / "altered.npz")


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (lambda a, h: h.update(version=99), "version 99 is not supported"),
        (lambda a, h: h.update(format="other"), "not a demo library"),
        (lambda a, h: a.pop("traj_offsets"), "missing array 'traj_offsets'"),
        (lambda a, h: a.__setitem__("clouds_n3", a["clouds_n3"].astype(np.float32)), "dtype"),
        (lambda a, h: a["clouds_n3"].__setitem__((0, 0), np.nan), "NaN"),
        (lambda a, h: a["cloud_offsets"].__setitem__(1, 10_000), "cloud_offsets"),
        (lambda a, h: h.update(keys=h["keys"][:-1]), "keys"),
    ],
)
def test_invalid_contents_give_a_clear_error(tmp_path, library, mutate, message):
    arrays, header = read_npz(library.save(tmp_path / "lib.npz"), "demo library")
    mutate(arrays, header)
    write_npz(tmp_path / "bad.npz", arrays, header)
    with pytest.raises(CorruptFileError, match=message):
        DemoLibrary.load(tmp_path / "bad.npz")


def test_not_a_zip_and_missing_header(tmp_path):
    (tmp_path / "junk.npz").write_text("hello")
    with pytest.raises(CorruptFileError, match="junk.npz"):
        DemoLibrary.load(tmp_path / "junk.npz")
    with zipfile.ZipFile(tmp_path / "nohdr.npz", "w") as zf:
        zf.writestr("x.txt", json.dumps({}))
    with pytest.raises(CorruptFileError):
        DemoLibrary.load(tmp_path / "nohdr.npz")
    with pytest.raises(FileNotFoundError):
        DemoLibrary.load(tmp_path / "missing.npz")


def test_library_rejects_duplicates_and_bad_segments(library):
    with pytest.raises(InvalidInputError, match="duplicate"):
        DemoLibrary([library[0], library[0]])
    with pytest.raises(InvalidInputError, match="NaN"):
        seg = library[0]
        DemoSegment(
            seg.key,
            0,
            0,
            seg.pre_nodes_k3,
            np.full((3, 3), np.nan),
            seg.trajectory,
            seg.post_nodes_k3,
        )
    with pytest.raises(InvalidInputError, match="no segment"):
        library.index_of("nope")

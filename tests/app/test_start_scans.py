"""The shipped start scans are those of the clouds the app stores for each level's starts, so the
app's Suggest scans nothing; `knotlab tasks scans` writes them and will not overwrite them."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from knotlab.app import cli, defaults
from knotlab.app.web.resources import load_resources
from knotlab.core.npzfile import read_npz
from knotlab.labeling_db.store import open_store
from tests.minilib import mini_library


@pytest.mark.parametrize("level", ["main", "hard"])
def test_the_shipped_scans_cover_every_start_the_app_stores(level, tmp_path) -> None:
    resources = load_resources(
        defaults.library_path(), defaults.task_set_path(level, "train"), top_k=5
    )
    note = resources.load_start_scans(defaults.scans_path(level, "train"))
    assert note.startswith("600 precomputed start scans"), note
    from knotlab.core.world.sim import RopeWorld

    with open_store(f"sqlite:///{tmp_path}/s.db", create=True) as store:
        resources.register_starts(store, level)
        starts = store.start_states_to_label()
        stored = [s.cloud_n3 for s in starts]  # what Suggest scores
        nodes = [store.get_state(s.state_id).rope_nodes_k3 for s in starts]
    assert all(resources.start_scans.get(c) is not None for c in stored)
    with RopeWorld() as world:  # what a tab observes when it shows the start, and ranks
        for rope in nodes[:: len(nodes) // 20]:
            world.reset(np.asarray(rope, dtype=float))
            assert resources.start_scans.get(resources.agent.observe(world)) is not None


def test_the_shipped_scans_regenerate_from_the_command(tmp_path) -> None:
    """Run as a user would (a fresh process: one BLAS thread, as every knotlab command)."""
    out = tmp_path / "scans_main_train.npz"
    argv = ["tasks", "scans", "--level", "main", "--tasks", "40", "--out", str(out)]
    subprocess.run([sys.executable, "-m", "knotlab.app.cli", *argv, "--no-progress"], check=True)
    shipped = defaults.scans_path("main", "train")  # made on this vector width
    if not shipped.exists():  # a width no file is shipped for: compare with the AVX-512 one
        shipped = defaults.scans_path("main", "train", kind="avx512")
    made, header = read_npz(out, "scans")
    stored, stored_header = read_npz(shipped, "scans")
    # The first 40 starts, two clouds each (the stored one and the one a tab observes).
    assert len(made["digests"]) == 80
    row_made = {str(d): i for i, d in enumerate(made["digests"])}
    row_stored = {str(d): i for i, d in enumerate(stored["digests"])}
    both = sorted(row_made.keys() & row_stored.keys())
    rows_made = [row_made[d] for d in both]
    rows_stored = [row_stored[d] for d in both]
    if header["made_on"] == stored_header["made_on"]:
        # The same kernel: every cloud is a shipped one and every number the same bits.
        assert len(both) == 80
        for name in ("ok_sa", "costs_sac", "grasp_sa"):
            assert np.array_equal(made[name][rows_made], stored[name][rows_stored], equal_nan=True)
        return
    # Another numeric kind (another width, or OpenBLAS kernels unusual for it, as on a Zen 5):
    # a cloud a tab observes from a stored rope may differ in its last bits (one of 600 on an
    # AVX2 EPYC against the AVX-512 box's file; the app then scans that start in full), and the
    # scans' numbers differ in theirs.
    assert len(both) >= 78, len(both)
    assert np.array_equal(made["ok_sa"][rows_made], stored["ok_sa"][rows_stored])
    # Numbers: all but a few within 0.2 % (AVX2 against AVX-512: 3 of 359,400 costs, where a
    # registration went another way, and 167 of 89,850 grasp distances of ~1 mm off by ~5 um)
    for name in ("costs_sac", "grasp_sa"):
        close = np.isclose(
            made[name][rows_made], stored[name][rows_stored], rtol=2e-3, atol=1e-9, equal_nan=True
        )
        assert close.mean() >= 0.99, (name, int((~close).sum()), close.size)


@pytest.mark.parametrize("task", ["overhand", "figure8"])
@pytest.mark.parametrize("level", ["main", "hard"])
@pytest.mark.parametrize("kind", ["avx512", "avx2"])
def test_each_cpu_kind_has_its_own_shipped_scans(task, level, kind) -> None:
    """The app uses a summary only on the CPU kind that made it, so each kind ships its own."""
    path = defaults.scans_path(level, "train", task, kind=kind)
    assert path.name == f"scans_{level}_train_{kind}.npz"
    _, header = read_npz(path, "scans")
    assert header["made_on"] == kind


def test_a_library_of_ones_own_uses_no_shipped_scans(tmp_path) -> None:
    resources = load_resources(defaults.library_path(), defaults.task_set_path("main", "train"), 5)
    assert "no precomputed start scans" in resources.load_start_scans(tmp_path / "none.npz")
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip")
    assert "not used" in resources.load_start_scans(bad)
    assert len(resources.start_scans) == 0


def test_tasks_scans_refuses_to_overwrite_and_writes_elsewhere(tmp_path, capsys) -> None:
    shipped = defaults.scans_path("main", "train")
    before = shipped.read_bytes()
    assert cli.main(["tasks", "scans", "--level", "main", "--no-progress"]) == 2
    assert "--force" in capsys.readouterr().err and shipped.read_bytes() == before
    lib = mini_library(2).save(tmp_path / "lib.npz")
    out = tmp_path / "scans.npz"
    argv = ["tasks", "scans", "--library", str(lib), "--out", str(out), "--no-progress"]
    argv += ["--tasks", "20"]  # the first 20 starts: two clouds each
    assert cli.main(argv) == 0
    assert "wrote 40 start-scan summaries of main" in capsys.readouterr().out
    resources = load_resources(lib, defaults.task_set_path("main", "train"), 1)
    assert resources.load_start_scans(out).startswith("40 precomputed")
    assert cli.main(argv) == 2  # its own file too: only with --force
    assert cli.main([*argv, "--force"]) == 0


def test_suggest_from_a_labelling_store_scans_nothing_the_shipped_scans_hold(
    tmp_path, capsys, monkeypatch
) -> None:
    from knotlab.core.selection.features import LibraryFeaturizer

    resources = load_resources(defaults.library_path(), defaults.task_set_path("main", "train"), 5)
    url = f"sqlite:///{tmp_path}/s.db"
    with open_store(url, create=True) as store:
        resources.register_starts(store, "main")

    def no_scan(*_args, **_kwargs):
        raise AssertionError("a start was scanned")

    monkeypatch.setattr(LibraryFeaturizer, "scan", no_scan)
    monkeypatch.setattr(LibraryFeaturizer, "landmark_weights", no_scan)
    capsys.readouterr()
    argv = ["suggest", "--db", url, "--json", "--no-progress", "--limit", "300"]
    assert cli.main(argv) == 0
    rows = json.loads(capsys.readouterr().out)
    assert len(rows) == 300 and rows[0]["rank"] == 1

"""`knotlab demos info|generate` on the mini library: summaries, and a refused overwrite."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from knotlab.app import cli
from tests.minilib import mini_library

pytestmark = pytest.mark.xdist_group("minilib")


def test_demos_info_summarises_a_library(tmp_path: Path, capsys) -> None:
    path = mini_library(2).save(tmp_path / "lib.npz")
    assert cli.main(["demos", "info", str(path)]) == 0
    text = capsys.readouterr().out
    assert f"hash {mini_library(2).content_hash()}" in text
    assert "segments:      6" in text and "start states:  2" in text
    assert cli.main(["demos", "info", str(path), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["segments"] == 6 and info["segments_per_step"] == {"0": 2, "1": 2, "2": 2}
    assert info["path"] == str(path)


def test_demos_generate_checks_out_first_then_saves_whole(tmp_path: Path, capsys, monkeypatch):
    from knotlab.core.demos import generation

    calls = []

    def fake_generate(n_starts, settings, *, workers, progress):  # the expert takes minutes
        calls.append((n_starts, settings.seed, workers, progress))
        return generation.GenReport(mini_library(2), 3, 2, {"0": 1}, 0.1)

    monkeypatch.setattr(generation, "generate_library", fake_generate)
    argv = ["demos", "generate", "--starts", "2", "--seed", "5", "--workers", "1", "--no-progress"]
    assert cli.main([*argv, "--out", str(tmp_path / "folder" / "lib")]) == 2  # no .npz: refused
    assert calls == [] and not (tmp_path / "folder").exists()
    out = tmp_path / "folder" / "lib.npz"
    assert cli.main([*argv, "--out", str(out)]) == 0
    assert calls == [(2, 5, 1, False)]
    assert "6 segments from 2 start states" in capsys.readouterr().out
    assert [p.name for p in out.parent.iterdir()] == ["lib.npz"]  # no temporary left
    assert cli.main(["demos", "info", str(out), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["hash"] == mini_library(2).content_hash()

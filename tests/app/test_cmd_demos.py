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


@pytest.mark.slow
def test_demos_generate_writes_one_demo_and_no_temporary(tmp_path: Path, capsys) -> None:
    out = tmp_path / "lib.npz"
    argv = ["demos", "generate", "--starts", "1", "--workers", "1", "--no-progress"]
    assert cli.main([*argv, "--out", str(out)]) == 0
    assert "3 segments from 1 start states" in capsys.readouterr().out
    assert [p.name for p in tmp_path.iterdir()] == ["lib.npz"]
    assert cli.main(["demos", "info", str(out), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["segments"] == 3

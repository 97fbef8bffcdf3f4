"""`knotlab tie`: the fixed sequence ties a knot and the picture is written whole."""

from __future__ import annotations

import json
from pathlib import Path

from knotlab.app import cli


def test_tie_writes_a_png_and_reports_the_knot(tmp_path: Path, capsys) -> None:
    out = tmp_path / "pics" / "knot.png"
    assert cli.main(["tie", "--out", str(out), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["knot"] is True and summary["png"] == str(out)
    assert [s["step"] for s in summary["steps"]] == [1, 2, 3]
    assert all(s["ok"] for s in summary["steps"])
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert [p.name for p in out.parent.iterdir()] == ["knot.png"]  # no temporary left

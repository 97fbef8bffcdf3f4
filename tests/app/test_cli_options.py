"""One rule for command-line defaults: --db everywhere, $KNOTLAB_DB_URL as its default."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from knotlab.app import cli


def test_knotlab_db_url_is_the_default_of_every_database_command(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    url = f"sqlite:///{tmp_path / 'env.db'}"
    monkeypatch.setenv("KNOTLAB_DB_URL", url)
    monkeypatch.chdir(tmp_path)
    assert cli.main(["db", "init"]) == 0
    assert (tmp_path / "env.db").exists() and not (tmp_path / "knotlab.db").exists()
    capsys.readouterr()
    assert cli.main(["db", "stats", "--json"]) == 0
    assert "schema_head" in json.loads(capsys.readouterr().out)
    out = tmp_path / "labels.jsonl"
    assert cli.main(["labels", "export", "--out", str(out)]) == 0
    assert out.exists()


def test_db_flag_overrides_the_environment(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("KNOTLAB_DB_URL", f"sqlite:///{tmp_path / 'env.db'}")
    assert cli.main(["db", "init", "--db", f"sqlite:///{tmp_path / 'flag.db'}"]) == 0
    assert (tmp_path / "flag.db").exists() and not (tmp_path / "env.db").exists()
    # the old spelling still works for scripts written before the flags were unified
    assert cli.main(["db", "upgrade", "--url", f"sqlite:///{tmp_path / 'flag.db'}"]) == 0


@pytest.mark.parametrize("command", ["db init", "db stats", "labels export", "label", "train"])
def test_every_database_command_takes_db(command: str) -> None:
    parser = cli.build_parser()
    args = parser.parse_args([*command.split(), *(["--oracle"] if command == "label" else [])])
    assert hasattr(args, "db")


def test_help_does_not_load_the_simulator_or_print_its_banner() -> None:
    res = subprocess.run(
        [sys.executable, "-m", "knotlab.app.cli", "--help"],
        capture_output=True,
        text=True,
        check=True,
    )
    assert "pybullet" not in res.stdout + res.stderr
    assert "bench" in res.stdout and "train" in res.stdout

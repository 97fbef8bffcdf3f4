"""Bad input to any command: exit code 2, one line on stderr, and no file written or changed.

Each case runs `knotlab.app.cli.main` in a scratch working directory holding a few bad files; the
files there and under static/ are hashed before and after, so a refused command that still wrote
(a database, a half output, a stray temporary) or replaced a shipped file fails the test.
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from knotlab.app import cli, defaults, options
from knotlab.core.demos.tasks import RopeTask, TaskSet
from knotlab.core.world.rope import straight_rope

LIBRARY = str(defaults.LIBRARY_PATH)
MODEL = str(defaults.MODEL_PATH)
TEST_TASKS = str(defaults.task_set_path("main", "test"))
TRAIN_TASKS = str(defaults.task_set_path("main", "train"))
NO_MYSQL_DRIVER = importlib.util.find_spec("MySQLdb") is None


def _rope_task_set(path: Path, n_nodes: int, length: float) -> None:
    task = RopeTask("t-0000", straight_rope(n_nodes, length, 0.01), 0, 1)
    TaskSet([task], {"split": "test", "level": "main"}).save(path)


@pytest.fixture
def workdir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A scratch working directory with bad inputs in it, and no database URL from outside."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("KNOTLAB_DB_URL", raising=False)
    monkeypatch.delenv(cli.DEBUG_ENV, raising=False)
    (tmp_path / "corrupt.npz").write_bytes(b"PK\x03\x04 this is not a whole zip file")
    (tmp_path / "notes.txt").write_text("a plain file: nothing can be written under it\n")
    (tmp_path / "bad.jsonl").write_text("{not json\n")
    (tmp_path / "somedir").mkdir()
    _rope_task_set(tmp_path / "small_rope.npz", 11, 1.0)  # 11 nodes: another rope
    _rope_task_set(tmp_path / "long_rope.npz", 41, 2.0)  # 2 m: another scale
    return tmp_path


def _snapshot(*folders: Path) -> dict[str, str]:
    return {
        str(p): hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else "folder"
        for folder in folders
        for p in sorted(folder.rglob("*"))
    }


GEN = ["demos", "generate", "--out", "lib.npz", "--workers", "1", "--no-progress"]
TASKS_GEN = ["tasks", "generate", "--seed", "0", "--out-dir", "out", "--no-progress"]
TRAIN = ["train", "--labels", "none.jsonl", "--out", "m.npz", "--no-progress"]
BENCH = ["bench", "--out-dir", "res", "--no-progress", "--workers", "1"]
LABEL = ["label", "--oracle", "--no-progress", "--workers", "1"]
PLAYBACK = ["playback", "res:nn:t-0000", "--out", "x.gif"]

CASES = [
    # --db: unknown dialects, missing drivers, not URLs, missing or foreign files
    (["db", "stats", "--db", "foo://bar"], "unknown database dialect 'foo'"),
    (["db", "init", "--db", "foo://bar"], "unknown database dialect 'foo'"),
    (["db", "upgrade", "--db", "postgresql+nosuchdriver://u@h/db"], "unknown database dialect"),
    pytest.param(
        ["db", "stats", "--db", "mysql://u@h/db"],
        "driver for 'mysql' is not installed",
        marks=pytest.mark.skipif(not NO_MYSQL_DRIVER, reason="MySQLdb is installed here"),
        id="missing-driver",
    ),
    (["db", "init", "--db", "not a url"], "is not a database URL"),
    (["db", "stats", "--db", "sqlite:///none.db"], "no such database"),
    (["db", "stats", "--db", "sqlite:///notes.txt"], "not an SQLite database"),
    (["labels", "export", "--db", "foo://bar", "--out", "x.jsonl"], "unknown database dialect"),
    (["train", "--db", "foo://bar", "--out", "m.npz", "--no-progress"], "unknown database"),
    # labels files
    (["labels", "export", "--format", "jsonl", "--out", "x.csv"], "says csv but --format is jsonl"),
    (["labels", "export", "--out", "x.txt"], "expected a .jsonl or .csv file name"),
    (["labels", "export", "--out", "notes.txt/x.jsonl"], "is a file, not a folder"),
    (["labels", "import", "none.jsonl"], "labels file not found"),
    (["labels", "import", "bad.jsonl"], "line 1"),
    (["labels", "import", "somedir"], "cannot tell the format"),
    # library, task-set and model files: missing, corrupt, the wrong kind, the wrong rope
    (["demos", "info", "none.npz"], "demo library file not found"),
    (["demos", "info", "corrupt.npz"], "cannot read demo library file"),
    (["demos", "info", TEST_TASKS], "not a demo library"),
    (["demos", "info", "somedir"], "is a folder"),
    (["tasks", "info", "none.npz"], "task set file not found"),
    (["tasks", "info", "corrupt.npz"], "cannot read task set file"),
    (["tasks", "info", LIBRARY], "not a task set"),
    (["tasks", "info", "small_rope.npz"], "ropes have 11 nodes; the simulated rope has 41"),
    (["tasks", "info", "long_rope.npz"], "rope arc length 2 m"),
    (["model", "info", "none.npz"], "model file not found"),
    (["model", "info", "corrupt.npz"], "not a readable knotlab model file"),
    (["model", "info", LIBRARY], "model file lacks"),
    # output paths, checked before any work
    ([*GEN[:2], "--out", "notes.txt/lib.npz"], "is a file, not a folder"),
    ([*GEN[:2], "--out", "somedir"], "is a folder"),
    ([*GEN[:2], "--out", "lib.txt"], "expected a .npz file name"),
    ([*GEN[:2], "--out", LIBRARY], "would replace a shipped or committed demo library"),
    (["tie", "--out", "notes.txt/knot.png"], "is a file, not a folder"),
    (["tie", "--out", "knot.txt"], "expected a .png file name"),
    ([*TRAIN[:3], "--out", "notes.txt/m.npz"], "is a file, not a folder"),
    ([*TRAIN[:3], "--out", MODEL], "would replace a shipped or committed model"),
    (["bench", "--out-dir", "notes.txt/res"], "is a file, not a folder"),
    (["bench", "--out-dir", "notes.txt"], "is a file; expected a folder"),
    (["bench", "--out", "notes.txt"], "--out-dir notes.txt is a file"),  # the old spelling
    ([*TASKS_GEN[:4], "--out-dir", "notes.txt"], "is a file; expected a folder"),
    ([*TASKS_GEN[:4], "--out-dir", str(defaults.LIBRARY_PATH.parent)], "would replace a shipped"),
    ([*TASKS_GEN, "--level", "../escape"], "argument --level: expected a plain name"),
    ([*TASKS_GEN, "--level", "a/b"], "argument --level"),
    ([*TASKS_GEN, "--train", "0", "--test", "0"], "nothing to generate"),
    # numbers: NaN, infinite, negative or zero where that means nothing
    ([*GEN, "--bend", "nan"], "argument --bend: expected a finite number >= 0"),
    ([*GEN, "--bend", "-0.01"], "argument --bend"),
    ([*GEN, "--starts", "0"], "argument --starts: expected an integer >= 1"),
    ([*GEN, "--seed", "-1"], "argument --seed: expected an integer >= 0"),
    ([*GEN, "--workers", "0"], "argument --workers"),
    ([*TASKS_GEN, "--rho", "-0.1"], "argument --rho: expected a finite number > 0"),
    ([*TASKS_GEN, "--rho", "inf"], "argument --rho"),
    ([*TASKS_GEN, "--centres", "0"], "argument --centres"),
    ([*TASKS_GEN, "--train", "-5"], "argument --train"),
    ([*TRAIN, "--margin-scale", "nan"], "argument --margin-scale"),
    ([*TRAIN, "--margin-scale", "0"], "argument --margin-scale"),
    ([*TRAIN, "--C", "nan"], "argument --C"),
    ([*TRAIN, "--D", "-1"], "argument --D"),
    ([*TRAIN, "--validation-fraction", "1"], "argument --validation-fraction"),
    ([*TRAIN, "--landmarks", "-1,2"], "argument --landmarks"),
    ([*BENCH, "--tasks", "0"], "argument --tasks: expected an integer >= 1"),
    ([*BENCH, "--noise", "-1"], "argument --noise"),
    ([*BENCH, "--noise", "nan"], "argument --noise"),
    ([*BENCH, "--max-steps", "0"], "argument --max-steps"),
    ([*BENCH, "--policies", "la99x99"], "argument --policies: la99x99: lookahead depth must"),
    ([*BENCH, "--policies", "la2x51"], "width 1-50, got depth 2, width 51"),
    ([*BENCH, "--policies", "la6x1"], "argument --policies"),
    ([*BENCH, "--policies", ","], "argument --policies: expected comma-separated"),
    ([*LABEL, "--tasks", "0"], "argument --tasks: expected an integer >= 1"),
    ([*LABEL, "--tasks", "train"], "argument --tasks: expected an integer"),  # now --split
    ([*LABEL, "--split", "dev"], "argument --split: invalid choice"),
    ([*LABEL, "--split", "test"], "'test' task set"),
    ([*LABEL, "--top", "0"], "argument --top"),
    ([*LABEL, "--level", "extreme"], "--level extreme: task 'overhand' has no such level"),
    ([*LABEL, "--task", "granny"], "argument --task: unknown task 'granny'; known tasks:"),
    ([*LABEL, "--sim-budget", "nan"], "argument --sim-budget: expected an integer"),
    ([*PLAYBACK, "--size", "0"], "argument --size: expected an integer from 64 to 2048, got '0'"),
    ([*PLAYBACK, "--size", "big"], "argument --size: expected an integer, got 'big'"),
    ([*PLAYBACK, "--fps", "0"], "argument --fps: expected an integer from 1 to 60"),
    ([*PLAYBACK, "--fps", "12.5"], "argument --fps"),
    ([*PLAYBACK, "--speed", "nan"], "argument --speed"),
    ([*PLAYBACK, "--speed", "0"], "argument --speed"),
    (["suggest", "--seed", "-1"], "argument --seed: expected an integer >= 0"),
    (["suggest", "--limit", "0"], "argument --limit: expected an integer >= 1"),
    (["suggest", "--db", "sqlite:///x.db", "--task-set", "t.npz"], "give --db or --task-set"),
    (["app", "--top", "10"], "argument --top: expected an integer from 1 to 9"),
    (["app", "--top-k", "0"], "argument --top-k: expected an integer from 1 to 9"),
    # inputs of the long-running commands, refused before they start
    (TRAIN, "none.jsonl: labels file not found"),
    ([*TRAIN, "--library", "corrupt.npz"], "cannot read demo library file"),
    ([*TASKS_GEN, "--library", "none.npz"], "demo library file not found"),
    ([*BENCH, "--library", "none.npz"], "demo library file not found"),
    ([*BENCH, "--task-set", "corrupt.npz"], "cannot read task set file"),
    ([*BENCH, "--task-set", "small_rope.npz"], "ropes have 11 nodes"),
    ([*BENCH, "--policies", "nn,bogus"], "argument --policies: unknown policy 'bogus'"),
    ([*BENCH, "--policies", "greedy", "--model", "none.npz"], "need a trained model"),
    ([*LABEL, "--task-set", "none.npz"], "task set file not found"),
    ([*LABEL, "--task-file", "long_rope.npz"], "rope arc length"),  # the old spelling
    ([*LABEL, "--task-set", TEST_TASKS], "'test' task set"),
    ([*LABEL, "--task-set", TRAIN_TASKS, "--library", "corrupt.npz"], "cannot read demo library"),
    # the command line itself
    (["frobnicate"], "invalid choice: 'frobnicate'"),
    (["demos"], "the following arguments are required"),
]


def _id(case) -> str:
    argv = case.values[0] if hasattr(case, "values") else case[0]
    return "-".join(a if len(a) < 24 else Path(a).name for a in argv)[:80]


@pytest.mark.parametrize(("argv", "message"), CASES, ids=[_id(c) for c in CASES])
def test_bad_input_fails_in_one_line_with_exit_code_2_and_writes_nothing(
    workdir: Path, capsys: pytest.CaptureFixture[str], argv: list[str], message: str
) -> None:
    before = _snapshot(workdir, defaults.STATIC_DIR, defaults.LIBRARY_PATH.parent)
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("knotlab"), err
    assert "Traceback" not in err
    assert message in lines[0], lines[0]
    assert ": error: " in lines[0]
    assert _snapshot(workdir, defaults.STATIC_DIR, defaults.LIBRARY_PATH.parent) == before


def _knotlab(*argv: str, cwd: Path, **env: str) -> subprocess.CompletedProcess[str]:
    environ = {k: v for k, v in os.environ.items() if k not in ("KNOTLAB_DB_URL", cli.DEBUG_ENV)}
    return subprocess.run(
        [sys.executable, "-m", "knotlab.app.cli", *argv],
        cwd=cwd,
        env={**environ, **env},
        capture_output=True,
        text=True,
        timeout=120,
    )


@pytest.mark.parametrize(
    "argv",
    [
        ["db", "stats", "--db", "foo://bar"],
        ["tasks", "generate", "--seed", "0", "--level", "../escape"],
        ["demos", "info", "corrupt.npz"],
    ],
)
def test_a_real_process_exits_2_with_one_line(workdir: Path, argv: list[str]) -> None:
    before = _snapshot(workdir)
    res = _knotlab(*argv, cwd=workdir)
    assert res.returncode == 2
    assert len(res.stderr.splitlines()) == 1 and res.stderr.startswith(f"knotlab {argv[0]}")
    assert res.stdout == ""
    assert _snapshot(workdir) == before


def test_debug_shows_the_traceback(workdir: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    res = _knotlab("--debug", "demos", "info", "corrupt.npz", cwd=workdir)
    assert res.returncode == 1 and "Traceback" in res.stderr and "CorruptFileError" in res.stderr
    res = _knotlab("demos", "info", "none.npz", cwd=workdir, KNOTLAB_DEBUG="1")
    assert "Traceback" in res.stderr and "FileNotFoundError" in res.stderr
    # in-process the error propagates to the caller
    from knotlab.core.errors import CorruptFileError

    with pytest.raises(CorruptFileError):
        cli.main(["--debug", "demos", "info", "corrupt.npz"])
    monkeypatch.setenv(cli.DEBUG_ENV, "1")
    with pytest.raises(FileNotFoundError):
        cli.main(["tasks", "info", "none.npz"])


def test_a_failed_run_exits_1_in_one_line(
    workdir: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    from knotlab.app import cmd_model
    from knotlab.core.errors import SolverError

    def solver_fails(args) -> int:
        raise SolverError("QP solver failed: primal infeasible")

    monkeypatch.setattr(cmd_model, "run_info", solver_fails)
    assert cli.main(["model", "info", MODEL]) == 1
    err = capsys.readouterr().err
    assert err == "knotlab model info: error: QP solver failed: primal infeasible\n"

    def bug(args) -> int:
        return {}["missing"]

    monkeypatch.setattr(cmd_model, "run_info", bug)
    assert cli.main(["model", "info", MODEL]) == 1
    (line,) = capsys.readouterr().err.splitlines()
    assert line.startswith("knotlab model info: error: unexpected KeyError") and "--debug" in line


def test_an_interrupted_command_says_so_in_one_line(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    from knotlab.app import cmd_model

    def interrupted(args) -> int:
        raise KeyboardInterrupt

    monkeypatch.setattr(cmd_model, "run_info", interrupted)
    assert cli.main(["model", "info", MODEL]) == 130
    assert capsys.readouterr().err == "knotlab model info: interrupted\n"


def test_version_is_the_packages_one(capsys: pytest.CaptureFixture[str]) -> None:
    from knotlab import __version__

    assert cli.main(["--version"]) == 0
    assert capsys.readouterr().out == f"knotlab {__version__}\n"
    assert cli.version() == __version__


@pytest.mark.parametrize(
    "command",
    [
        "label --oracle",
        "train",
        "bench --out r",
        "demos generate --out x.npz",
        "tasks generate --seed 0",
    ],
)
def test_every_command_with_a_progress_bar_takes_no_progress(command: str) -> None:
    args = cli.build_parser().parse_args([*command.split(), "--no-progress"])
    assert args.no_progress is True


def test_one_flag_names_a_task_set_file_and_the_old_spellings_still_work() -> None:
    parser = cli.build_parser()
    for command in (
        "label --oracle",
        "bench --out-dir r",
        "suggest",
        "playback r:nn:t --out x.gif",
    ):
        for flag in ("--task-set", "--task-file", "--tasks-file"):
            args = parser.parse_args([*command.split(), flag, "t.npz"])
            assert args.task_set == "t.npz"
        sub = parser.parse_args(command.split())
        assert sub.task_set is None
    assert "--task-file" not in parser.format_help()


def test_numbers_are_read_exactly(capsys: pytest.CaptureFixture[str]) -> None:
    args = cli.build_parser().parse_args([*TASKS_GEN, "--rho", "0.02", "--train", "0"])
    assert args.rho == 0.02 and args.train == 0
    assert np.isfinite(args.rho)
    # --level is the task's first level unless given
    assert args.level is None and options.resolve_level(args, shipped=False) == "main"
    assert args.level == "main"

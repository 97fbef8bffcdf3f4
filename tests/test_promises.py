"""The README's promises about the command line, each stated once and checked on every command.

README, "The command line": every command has `--help`; bad input gives one line naming the
problem (exit 2), a failed run exit 1, `--debug` the traceback. An output path that exists is
written only with `--force`, unless it is the command's own output to resume; one that is shipped
or committed (`static/`, `results/`, a task's data) only with `--force`, resuming included.

Each test walks the whole parser tree (`cli.build_parser`), so a command is held to every promise
as soon as it is registered. What a command needs to get as far as the check is filled in from
what its parser declares: a required switch, a choice, a number, an input file of the kind its
flag names (`options.is_input`), an --out file with the suffix its help names. The little that no
parser says (how a command uses --db, what an --out-dir holds) is in tables below, and a command
missing from them fails the test that needs it. Commands run in-process (`cli.main`) in a scratch
working directory; every check is one that must fail before any work starts, so the file is fast.
"""

from __future__ import annotations

import argparse
import hashlib
import re
import types
from pathlib import Path

import pytest

from knotlab.app import cli, defaults, options
from tests.app.test_cli_flags import _commands, _reads_numbers

# Each check ends before any work starts: a command still running after this long did not check.
pytestmark = pytest.mark.timeout(60)

README = Path(__file__).resolve().parents[1] / "README.md"
PARSERS: dict[str, argparse.ArgumentParser] = dict(_commands(cli.build_parser()))
LEAVES = sorted(
    c
    for c, p in PARSERS.items()
    if c and not any(isinstance(a, argparse._SubParsersAction) for a in p._actions)
)
SOMEONE_ELSES = b"someone else's file: not to be replaced\n"

# How each command uses --db: it reads an existing database (a missing one is bad input), or it
# creates one (a missing one is made: nothing to refuse). A reader's values that get it to the
# database are given with it, by the dest of their argument.
DB_READERS: dict[str, dict[str, str]] = {
    "db upgrade": {},
    "db stats": {},
    "labels export": {},
    "labels agreement": {},
    "train": {},
    "suggest": {},
    "playback": {"episode": "db:1"},  # a stored episode (RESULTS_DIR:POLICY:TASK_ID is not)
}
DB_CREATORS = {"db init", "label", "labels import", "app"}

# Commands that read no file at all, and why.
NO_INPUTS = {
    "tie": "ties a straight rope with the fixed sequence",
    "demos generate": "runs the scripted expert on seeded ropes",
    "db init": "a database URL only (DB_CREATORS)",
    "db upgrade": "a database URL only (DB_READERS)",
    "db stats": "a database URL only (DB_READERS)",
    "labels agreement": "a database URL only (DB_READERS)",
}

# A missing input in the form its argument takes ({} is the missing path).
MISSING_FORMS = {("playback", "episode"): "{}:nn:main-test-0000"}

# What an --out-dir holds that its command writes: the file a test puts there first.
OUT_DIR_FILES = {"bench": "results.json", "tasks generate": "tasks_main_train.npz"}

# Outputs that are resumed, never replaced: another kind of file there is refused even with
# --force (so the message need not offer --force).
NEVER_MIXED = {"labels tries": "appends to its own tries file of the same labels only"}

SUFFIX = re.compile(r"\.(npz|jsonl|csv|gif|mp4|png|h5|hdf5|json)\b")
SUFFIX_WORD = re.compile(r"\b(npz|jsonl|csv|gif|png|h5|json)\b")


def _params(pairs: list[tuple[str, str]]) -> list:
    """Parameters (command, argument) named 'command argument'."""
    return [pytest.param(c, a, id=f"{c} {a}") for c, a in pairs]


def _words(command: str) -> list[str]:
    return command.split()


def _option(command: str, name: str) -> argparse.Action | None:
    return next((a for a in PARSERS[command]._actions if name in a.option_strings), None)


def _out_name(action: argparse.Action, stem: str = "out") -> str:
    """A file name with the suffix the --out help names ('the library (.npz)' -> out.npz)."""
    text = str(action.help or "")
    match = SUFFIX.search(text) or SUFFIX_WORD.search(text.lower())
    return f"{stem}.{match.group(1)}" if match else stem


def _value(command: str, action: argparse.Action, files: dict[str, str]) -> str:
    """A value that gets a required argument past parsing and its own checks."""
    if action.choices is not None:
        return str(next(iter(action.choices)))
    if _reads_numbers(action):
        return "1"
    if options.is_input(action):
        return files.get(action.dest, files["path"])
    if action.dest == "out":
        return _out_name(action)
    if action.dest == "out_dir":
        return "out-dir"
    return "x"


def _argv(
    command: str,
    files: dict[str, str],
    *,
    skip: tuple[str, ...] = (),
    values: dict[str, str] | None = None,
) -> list[str]:
    """``command`` with every required argument filled in (but those named in ``skip``; those in
    ``values``, by dest, as given there)."""
    values = values or {}
    argv = _words(command)
    for action in PARSERS[command]._actions:
        if isinstance(action, argparse._HelpAction) or action.dest in skip:
            continue
        positional = not action.option_strings
        if positional and action.nargs in ("?", "*"):
            continue
        if not positional and (not action.required or set(action.option_strings) & set(skip)):
            continue
        if action.nargs == 0:
            argv.append(action.option_strings[0])
            continue
        value = values.get(action.dest) or _value(command, action, files)
        argv += [value] if positional else [action.option_strings[0], value]
    for group in PARSERS[command]._mutually_exclusive_groups:
        # a required choice between flags (label's --oracle | --search): its first flag
        first = group._group_actions[0]
        if group.required and first.nargs == 0 and first.dest not in skip:
            argv.append(first.option_strings[0])
    return argv


def _snapshot(folder: Path) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        if p.is_file()
        else "folder"
        for p in sorted(folder.rglob("*"))
    }


def _one_line(capsys: pytest.CaptureFixture[str], command: str) -> str:
    """The one line a refused command printed: 'knotlab <command>: error: ...'."""
    err = capsys.readouterr().err
    lines = err.splitlines()
    assert len(lines) == 1, f"knotlab {command}: expected one line on stderr, got:\n{err}"
    assert "Traceback" not in err
    assert lines[0].startswith(f"knotlab {command}: error: "), lines[0]
    return lines[0]


@pytest.fixture
def workdir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A scratch working directory, and no database URL, token or debug switch from outside."""
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    for name in (options.DB_ENV, cli.DEBUG_ENV, "KNOTLAB_TOKEN"):
        monkeypatch.delenv(name, raising=False)
    return work


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, str]:
    """Valid input files by the dest of the argument that reads them."""
    from datetime import UTC, datetime

    from knotlab.labeling_db.interchange import write_labels
    from knotlab.labeling_db.store import StoredExecution
    from tests.db_fixtures import make_execution

    labels = tmp_path_factory.mktemp("inputs") / "labels.jsonl"
    when = datetime(2024, 1, 1, tzinfo=UTC)
    with open(labels, "w", encoding="utf-8") as fh:
        item = StoredExecution(make_execution("e0"), started_at=when, finished_at=when)
        write_labels([item], fh, "jsonl")
    return {
        "labels": str(labels),
        "library": str(defaults.LIBRARY_PATH),
        "task_set": str(defaults.task_set_path("main", "test")),
        "model": str(defaults.MODEL_PATH),
        "path": str(defaults.LIBRARY_PATH),  # any existing file of this project
    }


@pytest.fixture
def shipped(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> dict[str, Path]:
    """Tmp stand-ins for static/, results/ and a task's data folder (nothing real is touched)."""
    places = {name: tmp_path / "repo" / name for name in ("static", "results", "data")}
    for folder in places.values():
        folder.mkdir(parents=True)
    monkeypatch.setattr(defaults, "STATIC_DIR", places["static"])
    monkeypatch.setattr(defaults, "RESULTS_DIR", places["results"])
    monkeypatch.setattr(defaults, "shipped_dirs", lambda: (places["data"], places["results"]))
    return places


def test_the_promises_are_the_readme_s() -> None:
    """The sentences these tests hold every command to are still the README's."""
    text = " ".join(README.read_text(encoding="utf-8").split())
    for promise in (
        "Every command has `--help`",
        "bad input gives one line naming the problem (exit 2), a failed run exit 1, "
        "`--debug` the traceback",
        "An output path that exists is written only with `--force`, unless it is the command's "
        "own output to resume",
        "one that is shipped or committed (`static/`, `results/`, a task's data) only with "
        "`--force`, resuming included",
    ):
        assert promise in text, promise


# --- Every command has --help -----------------------------------------------------------------


@pytest.mark.parametrize("command", sorted(PARSERS), ids=lambda c: c or "knotlab")
def test_every_command_has_help(command: str, capsys: pytest.CaptureFixture[str]) -> None:
    """Every command has `--help`."""
    assert cli.main([*_words(command), "--help"]) == 0
    out, err = capsys.readouterr()
    assert out.startswith(f"usage: {' '.join(['knotlab', *_words(command)])}"), out[:200]
    assert err == ""


# --- Bad input: one line naming the problem, exit 2 ---------------------------------------------

NUMBER_FLAGS = [
    (command, option)
    for command in LEAVES
    for action in PARSERS[command]._actions
    if action.option_strings and action.nargs != 0 and _reads_numbers(action)
    for option in action.option_strings
]


@pytest.mark.parametrize(("command", "option"), _params(NUMBER_FLAGS))
def test_a_bad_number_is_one_line_naming_the_flag(
    command: str, option: str, workdir: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Bad input gives one line naming the problem (exit 2): a number flag's bad value."""
    for bad in ("nan", "1e999"):
        assert cli.main([*_words(command), option, bad]) == 2
        line = _one_line(capsys, command)
        assert f"argument {option}: " in line and repr(bad) in line, line
    assert _snapshot(workdir) == {}


def _inputs(command: str) -> list[argparse.Action]:
    return [a for a in PARSERS[command]._actions if options.is_input(a)]


INPUTS = [
    (c, a.option_strings[0] if a.option_strings else a.dest) for c in LEAVES for a in _inputs(c)
]


def test_every_command_s_files_are_known_as_inputs_or_outputs() -> None:
    """Each command either reads a file the walk finds, or NO_INPUTS says why it reads none; and
    no argument that names a file is left unmarked (a new one: `options.reads` it)."""
    problems = []
    for command in LEAVES:
        has_inputs = bool(_inputs(command))
        if has_inputs == (command in NO_INPUTS):
            problems.append(
                f"{command}: reads files {[a.dest for a in _inputs(command)]} but is in NO_INPUTS"
                if has_inputs
                else f"{command}: no argument marked as an input: mark its input files with "
                "options.reads, or list it in NO_INPUTS with why it reads none"
            )
        for action in PARSERS[command]._actions:
            names = f"{action.metavar or ''} {action.dest}".upper()
            looks_like_file = any(w in names for w in ("PATH", "FILE"))
            output = action.dest in ("out", "out_dir")
            if looks_like_file and not output and not options.is_input(action):
                problems.append(f"{command} {action.dest}: names a file but is not marked")
        if _option(command, "--db") is not None and command not in {*DB_READERS, *DB_CREATORS}:
            problems.append(f"{command} takes --db: add it to DB_READERS or DB_CREATORS")
    assert not problems, "\n".join(problems)


@pytest.mark.parametrize(("command", "argument"), _params(INPUTS))
def test_a_missing_input_is_one_line(
    command: str,
    argument: str,
    workdir: Path,
    files: dict[str, str],
    capsys: pytest.CaptureFixture[str],
) -> None:
    """Bad input gives one line naming the problem (exit 2): an input file that is not there."""
    action = _option(command, argument) or next(
        a for a in PARSERS[command]._actions if a.dest == argument
    )
    missing = workdir.parent / f"missing-{action.dest}.npz"
    value = MISSING_FORMS.get((command, action.dest), "{}").format(missing)
    argv = _argv(command, files, skip=(action.dest,))
    argv += [value] if not action.option_strings else [argument, value]
    assert cli.main(argv) == 2
    line = _one_line(capsys, command)
    assert missing.stem in line, line
    assert _snapshot(workdir) == {}, "a refused command wrote into the working directory"


@pytest.mark.parametrize("command", sorted(DB_READERS))
def test_a_missing_database_is_one_line(
    command: str, workdir: Path, files: dict[str, str], capsys: pytest.CaptureFixture[str]
) -> None:
    """Bad input gives one line naming the problem (exit 2): a database file that is not there."""
    missing = workdir.parent / "missing.db"
    argv = [*_argv(command, files, values=DB_READERS[command]), "--db", f"sqlite:///{missing}"]
    assert cli.main(argv) == 2
    assert "missing.db" in _one_line(capsys, command)
    assert not missing.exists()
    assert _snapshot(workdir) == {}


@pytest.mark.parametrize("command", LEAVES)
def test_a_failed_run_exits_1_and_debug_shows_the_traceback(
    command: str,
    workdir: Path,
    files: dict[str, str],
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """A failed run exit 1, `--debug` the traceback."""
    parser = cli.build_parser()

    def fails(args: argparse.Namespace) -> int:  # the command's run, failing on good input
        raise RuntimeError("the run failed")

    dict(_commands(parser))[command].set_defaults(func=fails)
    argv = _argv(command, files)
    with monkeypatch.context() as patch:
        patch.setattr(cli, "build_parser", lambda: parser)
        assert cli.main(argv) == 1
        line = _one_line(capsys, command)
        assert "RuntimeError: the run failed" in line and "--debug" in line, line
        with pytest.raises(RuntimeError, match="the run failed"):  # the traceback, not a line
            cli.main(["--debug", *argv])
        patch.setenv(cli.DEBUG_ENV, "1")
        with pytest.raises(RuntimeError, match="the run failed"):
            cli.main(argv)
    # bad input too: one line without --debug (above), the exception itself with it
    for action in _inputs(command)[:1]:
        missing = workdir.parent / f"missing-{action.dest}.npz"
        value = MISSING_FORMS.get((command, action.dest), "{}").format(missing)
        argv = _argv(command, files, skip=(action.dest,))
        argv += [value] if not action.option_strings else [action.option_strings[0], value]
        with pytest.raises(Exception, match=missing.stem):
            cli.main(["--debug", *argv])


# --- Outputs ----------------------------------------------------------------------------------

OUTPUTS = [
    (c, flag) for c in LEAVES for flag in ("--out", "--out-dir") if _option(c, flag) is not None
]


def _existing_output(command: str, flag: str, where: Path) -> tuple[Path, Path]:
    """An output for ``flag`` in ``where`` that holds someone else's file: (the path to give,
    the file inside it)."""
    action = _option(command, flag)
    assert action is not None
    if flag == "--out":
        path = where / _out_name(action, "someone-else")
        target = path
    else:
        assert command in OUT_DIR_FILES, (
            f"{command} {flag}: add the file it writes to OUT_DIR_FILES"
        )
        path = where / "someone-elses-folder"
        path.mkdir()
        target = path / OUT_DIR_FILES[command]
    target.write_bytes(SOMEONE_ELSES)
    return path, target


@pytest.mark.parametrize(("command", "flag"), _params(OUTPUTS))
def test_an_existing_output_is_written_only_with_force(
    command: str,
    flag: str,
    workdir: Path,
    files: dict[str, str],
    capsys: pytest.CaptureFixture[str],
) -> None:
    """An output path that exists is written only with `--force`, unless it is the command's own
    output to resume."""
    path, target = _existing_output(command, flag, workdir)
    before = _snapshot(workdir)
    argv = [*_argv(command, files, skip=(flag,)), flag, str(path)]
    assert cli.main(argv) == 2
    line = _one_line(capsys, command)
    assert str(path) in line, line
    if command in NEVER_MIXED:  # another kind of file is not appended to, not even when told to
        assert cli.main([*argv, "--force"]) == 2
        assert str(path) in _one_line(capsys, command)
    else:
        assert "--force" in line, line
    assert target.read_bytes() == SOMEONE_ELSES
    assert _snapshot(workdir) == before


@pytest.mark.parametrize(("command", "flag"), _params(OUTPUTS))
@pytest.mark.parametrize("place", ["static", "results", "data"])
def test_a_shipped_or_committed_output_is_written_only_with_force(
    command: str,
    flag: str,
    place: str,
    shipped: dict[str, Path],
    workdir: Path,
    files: dict[str, str],
    capsys: pytest.CaptureFixture[str],
) -> None:
    """One that is shipped or committed (`static/`, `results/`, a task's data) only with
    `--force`, resuming included."""
    if flag == "--out":
        path, _ = _existing_output(command, flag, shipped[place])
    else:  # a committed folder: an existing one there, whatever it holds
        path = shipped[place] / "run"
        path.mkdir()
    before = _snapshot(shipped[place])
    assert cli.main([*_argv(command, files, skip=(flag,)), flag, str(path)]) == 2
    line = _one_line(capsys, command)
    assert "shipped or committed" in line and "--force" in line, line
    assert _snapshot(shipped[place]) == before
    assert _snapshot(workdir) == {}


@pytest.mark.parametrize("place", ["static", "results", "data"])
def test_the_output_rule_lets_force_through_and_nothing_else(
    place: str, shipped: dict[str, Path]
) -> None:
    """One that is shipped or committed only with `--force`, resuming included (the rule every
    command calls before it starts, `options.check_output`)."""
    from knotlab.core.errors import OutputPathError

    existing = shipped[place] / "thing.npz"
    existing.write_bytes(SOMEONE_ELSES)
    for resume in (None, lambda p: True):  # a committed output of its own: still --force
        with pytest.raises(OutputPathError, match="shipped or committed.*--force"):
            options.check_output(existing, force=False, resume=resume)
        assert options.check_output(existing, force=True, resume=resume) == existing
    folder = shipped[place] / "run"
    folder.mkdir()
    with pytest.raises(OutputPathError, match="shipped or committed"):
        options.check_output(folder, force=False, folder=True, writes=("a.json",))
    assert options.check_output(folder, force=True, folder=True) == folder
    new = shipped[place] / "new.npz"  # not there yet: nothing committed to protect
    assert options.check_output(new, force=False) == new
    assert options.in_shipped_place(new) and not options.is_committed(new)
    assert existing.read_bytes() == SOMEONE_ELSES


def test_the_repository_s_shipped_files_count_as_committed(project_root: Path) -> None:
    """One that is shipped or committed (`static/`, `results/`, a task's data) only with
    `--force`: the real places are the protected ones."""
    for path in (
        project_root / "static" / "readme_knot.png",
        project_root / "results" / "table1_main",
        defaults.LIBRARY_PATH,
        defaults.MODEL_PATH,
    ):
        assert path.exists() and options.is_committed(path), path
    assert not options.is_committed(project_root / "README.md")
    assert options.in_shipped_place(project_root / "results" / "not-yet")


# --- The app's Export GIF follows the same rule, without a --force to give ---------------------


def test_export_gif_never_replaces_a_file_it_did_not_write(tmp_path: Path) -> None:
    """An output path that exists is written only with `--force`: the app has none to give, so its
    export takes the next free name and rewrites only its own files."""
    from knotlab.app.web.playback_panel import export_name, save_export

    stem = export_name("la2x5 on main-test-0000")
    assert stem == "la2x5-on-main-test-0000"
    assert export_name("../../static/x y") == "static-x-y"  # no folders: a plain name
    folder = tmp_path / "exports"
    folder.mkdir()
    theirs = folder / f"{stem}.gif"
    theirs.write_bytes(SOMEONE_ELSES)
    (folder / f"{stem}-1.gif").write_bytes(SOMEONE_ELSES)
    own: set[Path] = set()
    first = save_export(b"GIF89a one", folder, stem, own)
    assert first == folder / f"{stem}-2.gif" and first.read_bytes() == b"GIF89a one"
    again = save_export(b"GIF89a two", folder, stem, own)  # its own file: rewritten
    assert again == first and first.read_bytes() == b"GIF89a two"
    other = save_export(b"GIF89a three", folder, "greedy-on-main-test-0001", own)
    assert other.name == "greedy-on-main-test-0001.gif"
    assert theirs.read_bytes() == SOMEONE_ELSES
    assert (folder / f"{stem}-1.gif").read_bytes() == SOMEONE_ELSES


def test_export_gif_never_writes_into_a_shipped_place(shipped: dict[str, Path]) -> None:
    """One that is shipped or committed (`static/`, `results/`, a task's data) only with
    `--force`: the app never writes there, new files included."""
    from knotlab.app.web.playback_panel import export_path
    from knotlab.core.errors import OutputPathError

    for folder in shipped.values():
        with pytest.raises(OutputPathError, match="shipped or committed"):
            export_path(folder / "exports", "x", set())
        assert _snapshot(folder) == {}


def test_export_gif_says_where_it_kept_the_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The Export GIF button (PlaybackPanel.export, without a browser): the download, and the
    file kept under a fresh name that the status line names."""
    from knotlab.app.web import playback_panel

    def fake_export(episode, library, path, **kwargs):
        Path(path).write_bytes(b"GIF89a fake")

    monkeypatch.setattr(playback_panel, "export_playback", fake_export)
    sent: list[tuple[str, bytes]] = []
    panel = playback_panel.PlaybackPanel.__new__(playback_panel.PlaybackPanel)
    panel.episode = types.SimpleNamespace(title="nn on main-test-0000")
    panel.library = object()
    panel.status = types.SimpleNamespace(content="")
    panel.client = types.SimpleNamespace(
        send_file_download=lambda name, data, save_immediately: sent.append((name, data))
    )
    panel.export_dir = tmp_path / "exports"
    panel._exported = set()
    panel.export_dir.mkdir()
    (panel.export_dir / "nn-on-main-test-0000.gif").write_bytes(SOMEONE_ELSES)
    panel.export()
    kept = panel.export_dir / "nn-on-main-test-0000-1.gif"
    assert sent == [(kept.name, b"GIF89a fake")]
    assert kept.read_bytes() == b"GIF89a fake"
    assert str(kept.resolve()) in panel.status.content
    assert (panel.export_dir / "nn-on-main-test-0000.gif").read_bytes() == SOMEONE_ELSES

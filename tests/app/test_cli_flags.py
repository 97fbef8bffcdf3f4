"""One meaning per flag: the whole `knotlab` argparse tree, walked command by command.

A flag name that several commands take must mean the same in all of them: it is declared once in
app/options.py (a `Flag`: one dest, one kind of value, one help sentence that a command may only
extend) and added with `options.add_flag`, which stamps the argparse action with its `Flag`.
A flag name that only one command takes is that command's own business. Every flag whose value
is a number, shared or not, takes a bounded type from app/options.py (the walk at the end).
"""

from __future__ import annotations

import argparse
from collections import defaultdict
from collections.abc import Iterator

import pytest

from knotlab.app import cli, options


def _commands(
    parser: argparse.ArgumentParser, path: tuple[str, ...] = ()
) -> Iterator[tuple[str, argparse.ArgumentParser]]:
    """Every (sub-)command parser of the tree, by its words ('labels tries'), recursively."""
    yield " ".join(path), parser
    seen: set[int] = set()
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                if id(sub) not in seen:  # an alias names the same parser again
                    seen.add(id(sub))
                    yield from _commands(sub, (*path, name))


def _flags() -> dict[str, dict[str, argparse.Action]]:
    """option string -> {command: its action}, over the whole tree (help and version aside)."""
    found: dict[str, dict[str, argparse.Action]] = defaultdict(dict)
    for command, parser in _commands(cli.build_parser()):
        for action in parser._actions:
            if isinstance(action, argparse._HelpAction):
                continue
            for option in action.option_strings:
                found[option][command] = action
    return found


def _kind(action: argparse.Action) -> str:
    """What a flag takes: a switch, a choice, or what its argparse type reads ('integer')."""
    if action.nargs == 0:
        return f"switch {type(action).__name__}"
    if action.choices is not None and action.type is None:
        return f"choice of {sorted(map(str, action.choices))}"
    return getattr(action.type, "__name__", "str").split()[0]


def _meaning(action: argparse.Action) -> tuple[object, ...]:
    """What a flag means in one command: its shared declaration, else its dest, kind and help."""
    shared = getattr(action, options.SHARED_ATTR, None)
    if shared is not None:
        return ("declared in options.py as", shared.name)
    return (action.dest, _kind(action), action.help)


def test_no_flag_name_has_two_meanings_and_shared_ones_are_declared_once() -> None:
    problems = []
    for option, by_command in sorted(_flags().items()):
        meanings: dict[tuple[object, ...], list[str]] = defaultdict(list)
        for command, action in by_command.items():
            meanings[_meaning(action)].append(command or "knotlab")
        if len(meanings) > 1:
            listed = "; ".join(f"{', '.join(c)}: {m}" for m, c in meanings.items())
            problems.append(f"{option} has {len(meanings)} meanings ({listed})")
        elif len(by_command) > 1 and next(iter(meanings))[0] != "declared in options.py as":
            problems.append(
                f"{option} is declared by hand in {', '.join(by_command)}: declare it once in "
                "app/options.py and add it with add_flag"
            )
    assert not problems, "\n".join(problems)


def test_shared_flags_keep_their_declared_dest_kind_and_help() -> None:
    declared = {name: flag for flag in options.FLAGS.values() for name in flag.spellings}
    problems = []
    kinds: dict[str, set[str]] = defaultdict(set)
    for option, by_command in sorted(_flags().items()):
        flag = declared.get(option)
        if flag is None:
            continue
        for command, action in by_command.items():
            where = f"{command} {option}"
            if getattr(action, options.SHARED_ATTR, None) is not flag:
                problems.append(f"{where}: re-declared by hand, not with add_flag")
                continue
            if action.dest != flag.dest:
                problems.append(f"{where}: dest {action.dest!r}, declared {flag.dest!r}")
            if action.help != argparse.SUPPRESS and not str(action.help).startswith(flag.help):
                problems.append(f"{where}: help {action.help!r} does not say {flag.help!r}")
            if flag.choices is not None:  # one vocabulary; a command takes the subset it can
                extra = set(action.choices or ()) - set(flag.choices)
                if extra:
                    problems.append(f"{where}: choices {sorted(extra)} are not declared")
            elif option == flag.name:
                kinds[option].add(_kind(action))
    problems += [
        f"{o}: takes {sorted(k)} in different commands" for o, k in kinds.items() if len(k) > 1
    ]
    assert not problems, "\n".join(problems)


def test_every_declared_flag_is_used_and_hidden_spellings_stay_hidden() -> None:
    flags = _flags()
    parser_help = {c: p.format_help() for c, p in _commands(cli.build_parser())}
    for flag in options.FLAGS.values():
        assert flag.name in flags, f"{flag.name} is declared in options.py but no command takes it"
        for alias in flag.aliases:
            for command in flags.get(alias, {}):
                assert f"{alias} " not in parser_help[command], (command, alias)


# The commands that load or write task data take --task; the others are listed here with why not.
TASK_COMMANDS = [
    "demos generate",
    "tasks generate",
    "tasks scans",
    "label",
    "labels tries",
    "train",
    "bench",
    "app",
    "playback",
    "suggest",
    "demos import",
    "serve",
    "model transfer",
]
NO_TASK_COMMANDS = {
    "tie": "runs the overhand knot's fixed sequence on a straight rope: no task files",
    "db init": "schema only",
    "db upgrade": "schema only",
    "db stats": "row counts",
    "labels export": "copies labels as they are",
    "labels import": "copies labels as they are",
    "labels agreement": "compares labellers' choices",
    "demos info": "describes the named file, whatever its task",
    "demos export": "copies the named library, whatever its task",
    "tasks info": "describes the named file, whatever its task",
    "model info": "describes the named file, whatever its task",
}


def test_every_command_is_either_task_aware_or_listed_as_not() -> None:
    leaves = {
        c
        for c, p in _commands(cli.build_parser())
        if c and not any(isinstance(a, argparse._SubParsersAction) for a in p._actions)
    }
    assert leaves == set(TASK_COMMANDS) | set(NO_TASK_COMMANDS)
    assert set(_flags()["--task"]) == set(TASK_COMMANDS)


@pytest.mark.parametrize("command", TASK_COMMANDS)
def test_task_defaults_to_overhand_and_unknown_tasks_fail_in_one_line(
    command: str, capsys: pytest.CaptureFixture[str]
) -> None:
    required = {
        "label": ["--oracle"],
        "labels tries": ["--labels", "l.jsonl", "--out", "t.jsonl"],
        "bench": ["--out-dir", "r"],
        "playback": ["r:nn:t-0", "--out", "x.gif"],
        "demos generate": ["--out", "x.npz"],
        "demos import": ["x.h5", "--out", "x.npz"],
        "tasks generate": ["--seed", "0"],
        "model transfer": ["m.npz", "--out", "x.npz"],
    }.get(command, [])
    parser = cli.build_parser()
    assert parser.parse_args([*command.split(), *required]).task == "overhand"
    assert cli.main([*command.split(), *required, "--task", "granny"]) == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1
    assert f"knotlab {command}: error: argument --task: unknown task 'granny'" in err
    assert "known tasks: overhand" in err


@pytest.mark.parametrize(
    ("argv", "dest", "value"),
    [
        # output folders are --out-dir; bench's --out DIR (README, scripts, results/) still
        # works as a unique prefix of --out-dir
        ("bench --out r", "out_dir", "r"),
        ("bench --out-dir r", "out_dir", "r"),
        ("app --top-k 3", "top", 3),  # hidden alias of --top
        ("labels tries --labels l.jsonl --out t.jsonl --top 7", "top", 7),
        ("label --oracle --top 4", "top", 4),  # was --candidates
        ("label --oracle --split train --tasks 3", "tasks", 3),  # was --tasks train --limit 3
        ("suggest --tasks-file t.npz", "task_set", "t.npz"),  # hidden alias of --task-set
        ("db init --url sqlite:///x.db", "db", "sqlite:///x.db"),  # hidden alias of --db
    ],
)
def test_documented_and_older_spellings_still_parse(argv: str, dest: str, value: object) -> None:
    assert getattr(cli.build_parser().parse_args(argv.split()), dest) == value


def test_renamed_flags_are_gone(capsys: pytest.CaptureFixture[str]) -> None:
    parser = cli.build_parser()
    for argv in ("label --oracle --candidates 3", "label --oracle --limit 3", "app --top-k2 3"):
        with pytest.raises(SystemExit):
            parser.parse_args(argv.split())
    assert "unrecognized arguments" in capsys.readouterr().err


# --- Every number a flag takes is bounded ---------------------------------------------------
#
# A flag whose value is a number (an int or float default, or a type that reads numbers) takes a
# bounded type from app/options.py (`integer`, `number`, `number_list`, `integer_tuple`, `PORT`,
# or a parser stamped with `options.bounded`), never bare int or float or no type at all: NaN,
# an infinity, a negative count or a typo like 1e9 then ends in one line when the command line is
# read, not minutes into a run.

_NUMBER_SAMPLES = ("1", "0.5", "1,2")


def _is_number(value: object) -> bool:
    if isinstance(value, (list, tuple)):
        return bool(value) and all(_is_number(v) for v in value)
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _reads_numbers(action: argparse.Action) -> bool:
    """A flag whose value is a number or numbers: by its default, or by what its type returns."""
    if _is_number(action.default) or action.type in (int, float):
        return True
    if options.is_bounded(action.type):
        return True
    if not callable(action.type):
        return False
    for sample in _NUMBER_SAMPLES:
        try:
            value = action.type(sample)
        except Exception:  # any refusal: the sample is not its kind of value
            continue
        if _is_number(value):
            return True
    return False


def unbounded_number_flags(parser: argparse.ArgumentParser) -> list[str]:
    """'command --flag: why' for every number flag of the tree without a bounded type (or whose
    bounded type lets NaN or an infinity through, or refuses its own default)."""
    problems = []
    for command, sub in _commands(parser):
        for action in sub._actions:
            if action.nargs == 0 or isinstance(
                action, (argparse._HelpAction, argparse._SubParsersAction)
            ):
                continue
            if not _reads_numbers(action):
                continue
            name = f"{command or 'knotlab'} {'/'.join(action.option_strings) or action.dest}"
            kind = getattr(action.type, "__name__", repr(action.type))
            if not options.is_bounded(action.type):
                problems.append(
                    f"{name}: a number flag with type {kind}; give it a bounded type from "
                    "app/options.py (integer, number, ...) so that a bad value fails in one line"
                )
                continue
            for bad in ("nan", "inf", "-1e999", "1e999"):
                try:
                    action.type(bad)
                except argparse.ArgumentTypeError:
                    continue
                problems.append(f"{name}: its type {kind} accepts {bad!r}")
            default = action.default
            if default is None or default == argparse.SUPPRESS:
                continue
            text = ",".join(map(str, default)) if isinstance(default, (list, tuple)) else default
            try:
                action.type(str(text))
            except argparse.ArgumentTypeError as exc:
                problems.append(f"{name}: the default {default!r} is out of its bounds ({exc})")
    return problems


def test_every_number_flag_of_every_command_has_a_bounded_type() -> None:
    assert unbounded_number_flags(cli.build_parser()) == []


def test_the_number_flag_walk_finds_an_unbounded_flag() -> None:
    """The walk above, proven on a made-up command that breaks the rule in every way it can."""
    parser = argparse.ArgumentParser(prog="fake")
    sub = parser.add_subparsers(dest="command")
    p = sub.add_parser("run")
    p.add_argument("--n", type=int, default=3)
    p.add_argument("--rate", default=0.5)  # no type: a number default, and text when given
    p.add_argument("--scale", type=float)
    p.add_argument("--counts", type=lambda s: [int(v) for v in s.split(",")])
    p.add_argument("--sloppy", type=options.bounded("says so")(lambda s: float(s)))
    p.add_argument("--tight", type=options.integer(5), default=3)  # a default out of bounds
    p.add_argument("--ok", type=options.integer(1), default=3)
    p.add_argument("--fine", type=options.number(0.0, above=True), default=0.5)
    p.add_argument("--name", default="x")
    p.add_argument("--flag", action="store_true")
    found = [problem.split(":")[0] for problem in unbounded_number_flags(parser)]
    assert found == ["run --n", "run --rate", "run --scale", "run --counts"] + [
        "run --sloppy"
    ] * 4 + ["run --tight"]


def test_lookahead_depth_and_width_are_bounded_when_the_command_line_is_read(
    capsys: pytest.CaptureFixture[str],
) -> None:
    parser = cli.build_parser()
    for policies in ("la99x99", "la6x1", "la1x51", "la99999999999999999999x1"):
        with pytest.raises(SystemExit) as exit_:  # parse time: before any file is read
            parser.parse_args(["bench", "--out-dir", "r", "--policies", policies])
        assert exit_.value.code == 2
        err = capsys.readouterr().err
        assert len(err.splitlines()) == 1, err
        assert f"argument --policies: {policies}: lookahead depth must be 1-5 and width" in err
    assert parser.parse_args(["bench", "--out-dir", "r", "--policies", "la5x50"]).policies == [
        "la5x50"
    ]

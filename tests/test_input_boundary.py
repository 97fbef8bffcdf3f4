"""Hostile input to every text reader ends in one clean KnotlabError (core.textinput).

A property test feeds random and mutated lines and files to each reader (labels JSONL and CSV,
tries JSONL, a bench's outcomes.jsonl, .npz headers, model metadata) and accepts only a result or
a one-line :class:`KnotlabError` that quotes little; then each probe that once broke a reader is
replayed through the command line: exit 2, one line on stderr, nothing written.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from knotlab.app import cli
from knotlab.core import textinput
from knotlab.core.errors import KnotlabError
from knotlab.core.experiments.bench.outcome_log import OutcomeLog
from knotlab.core.npzfile import read_npz
from knotlab.core.selection.qmodel import QModel
from knotlab.core.selection.tries import read_tries
from knotlab.labeling_db.interchange import read_labels
from knotlab.labeling_db.store import open_store
from tests.db_fixtures import make_execution

MAX_MESSAGE = 1000  # characters: a message quotes at most ~80 of a bad value
HEADER = '{"format":"knotlab-labels","version":1}'


@pytest.fixture(scope="module")
def labels(tmp_path_factory: pytest.TempPathFactory) -> dict[str, bytes]:
    """A valid labels file in each format (two small executions), as bytes."""
    folder = tmp_path_factory.mktemp("labels")
    url = f"sqlite:///{folder / 'src.db'}"
    with open_store(url) as store:
        store.add_executions(
            [make_execution(f"e{i}", n_steps=2, n_points=3, n_dead=1, seed=i) for i in range(2)]
        )
    out = {}
    for fmt in ("jsonl", "csv"):
        path = folder / f"labels.{fmt}"
        assert cli.main(["labels", "export", "--db", url, "--out", str(path)]) == 0
        out[fmt] = path.read_bytes()
    return out


TRIES_LINE = json.dumps(
    {
        "execution_id": "e0",
        "step_index": 0,
        "stage_before": 0,
        "tried": [{"demo": "s000-t0", "stage": 1, "knot": False, "failure": None}],
    }
)
OUTCOME_LINE = json.dumps(
    {"policy": "nn", "task_id": "t-0", "success": True, "failure_kind": None, "chosen": ["a"]}
)


def _write_npz(path: Path, member: str, payload: bytes) -> None:
    np.savez(path, **{member: np.frombuffer(payload, dtype=np.uint8)}, a=np.zeros(3))


READERS: dict[str, tuple[str, Callable[[Path], Any]]] = {
    "labels-jsonl": ("labels.jsonl", read_labels),
    "labels-csv": ("labels.csv", read_labels),
    "tries": ("tries.jsonl", read_tries),
    "outcomes-strict": ("outcomes.jsonl", lambda p: OutcomeLog(p).load(strict=True)),
    "outcomes": ("outcomes.jsonl", lambda p: OutcomeLog(p).load()),
    "npz-header": ("h.npz", lambda p: read_npz(p, "demo library")),
    "model-meta": ("m.npz", QModel.load),
}


def _valid(reader: str, labels: dict[str, bytes]) -> bytes:
    if reader == "labels-jsonl":
        return labels["jsonl"]
    if reader == "labels-csv":
        return labels["csv"]
    if reader == "tries":
        return (TRIES_LINE + "\n").encode()
    if reader.startswith("outcomes"):
        return (OUTCOME_LINE + "\n" + OUTCOME_LINE.replace("t-0", "t-1") + "\n").encode()
    return json.dumps({"format": "knotlab-demo-library", "version": 1, "n": 3}).encode()


def _read(reader: str, folder: Path, content: bytes) -> None:
    """Run one reader on ``content``; only a result or a clean one-line KnotlabError passes."""
    name, read = READERS[reader]
    path = folder / name
    if name.endswith(".npz"):
        _write_npz(path, "meta" if reader == "model-meta" else "header_json", content)
    else:
        path.write_bytes(content)
    try:
        read(path)
    except KnotlabError as exc:  # any other exception type fails the test
        message = str(exc)
        assert "\n" not in message and "\r" not in message, message[:300]
        assert "\u2028" not in message and len(message) < MAX_MESSAGE, message[:300]


# --- strategies: random JSON, hostile fragments, and mutations of a valid file

HOSTILE = st.sampled_from(
    [
        b"\xff",
        b"\xc3",
        "\u2028".encode(),
        "\u2029".encode(),
        b"\x85",
        b"\r",
        b"\x00",
        b"\\ud800",
        b'"\\ud800"',
        b"[" * 300,
        b"[" * 3000,
        b"{" * 70 + b"}" * 70,
        b"9" * 5000,
        b"-" + b"9" * 25,
        b"1e400",
        b"NaN",
        b'"9999-12-31T23:59:59-05:00"',
        b'"0001-01-01T00:00:00+05:00"',
        b'"2026-13-45"',
        b"x" * 3000,
        b'"' + b"y" * 3000 + b'"',
        b"\n",
        b",",
        b'"',
    ]
)
HOSTILE_VALUES = st.sampled_from(
    [
        "9999-12-31T23:59:59-05:00",
        "0001-01-01T00:00:00+05:00",
        "2026-01-01T00:00:00",
        "x" * 3000,
        "a\u2028b\n",
        "\x00",
        "",
        "progressed",
        "knot",
        "completed",
        "human",
        2**31,
        2**63 - 1,
        -(2**63),
        -1,
        [[1.0, 2.0, 3.0]],
        [[1.0, 2.0]],
        [["a", "b", "c"]],
    ]
)
JSON_VALUES = st.recursive(
    HOSTILE_VALUES
    | st.none()
    | st.booleans()
    | st.integers(min_value=-(2**70), max_value=2**70)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=30),
    lambda children: (
        st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=8), children, max_size=4)
    ),
    max_leaves=12,
)


def _replace_field(line: bytes, draw: st.DrawFn) -> bytes:
    """A JSON line with one field (top level or in its first step) set to a random value."""
    try:
        record = json.loads(line)
    except ValueError:
        return line
    if not isinstance(record, dict) or not record:
        return line
    target = record
    if isinstance(record.get("steps"), list) and record["steps"] and draw(st.booleans()):
        target = record["steps"][0]
    elif isinstance(record.get("tried"), list) and record["tried"] and draw(st.booleans()):
        target = record["tried"][0]
    if not isinstance(target, dict) or not target:
        return line
    key = draw(st.sampled_from(sorted(target)))
    target[key] = draw(JSON_VALUES)
    return json.dumps(record, ensure_ascii=draw(st.booleans())).encode("utf-8", "surrogatepass")


@st.composite
def mutated(draw: st.DrawFn, valid: bytes) -> bytes:
    """``valid`` with a few random edits: bytes replaced, hostile fragments inserted, lines
    dropped, cut or duplicated, fields of JSON lines replaced by random values."""
    lines = valid.split(b"\n")
    for _ in range(draw(st.integers(1, 3))):
        i = draw(st.integers(0, max(0, len(lines) - 1)))
        line = lines[i] if lines else b""
        kind = draw(st.sampled_from(["field", "insert", "byte", "cut", "drop", "dup", "random"]))
        if kind == "field":
            line = _replace_field(line, draw)
        elif kind == "insert":
            at = draw(st.integers(0, len(line)))
            line = line[:at] + draw(HOSTILE) + line[at:]
        elif kind == "byte" and line:
            at = draw(st.integers(0, len(line) - 1))
            line = line[:at] + bytes([draw(st.integers(0, 255))]) + line[at + 1 :]
        elif kind == "cut":
            line = line[: draw(st.integers(0, len(line)))]
        elif kind == "drop" and lines:
            del lines[i]
            continue
        elif kind == "dup":
            lines.insert(i, line)
        else:
            line = draw(st.binary(max_size=80) | JSON_VALUES.map(lambda v: json.dumps(v).encode()))
        if lines:
            lines[i] = line
        else:
            lines.append(line)
    return b"\n".join(lines)


@pytest.mark.parametrize("reader", sorted(READERS))
@settings(
    max_examples=120,
    derandomize=True,  # the suite is reproducible; explore more with a bigger max_examples
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(data=st.data())
def test_every_reader_fails_on_hostile_input_with_one_clean_line(
    reader: str, data: st.DataObject, labels: dict[str, bytes], tmp_path: Path
) -> None:
    content = data.draw(mutated(_valid(reader, labels)) | st.binary(max_size=300), label="file")
    _read(reader, tmp_path, content)


@pytest.mark.parametrize("fmt", ["jsonl", "csv"])
@settings(
    max_examples=25,
    derandomize=True,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(data=st.data())
def test_labels_import_stores_or_refuses_in_one_line(
    fmt: str, data: st.DataObject, labels: dict[str, bytes], tmp_path: Path, capsys
) -> None:
    """Past the reader, into a store: what validates is stored, what does not is one line."""
    content = data.draw(mutated(labels[fmt]), label="file")
    run = len(list(tmp_path.iterdir()))
    path, db = tmp_path / f"in{run}.{fmt}", tmp_path / f"k{run}.db"
    path.write_bytes(content)
    capsys.readouterr()
    code = cli.main(["labels", "import", str(path), "--db", f"sqlite:///{db}"])
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and "error: unexpected" not in err, err[:500]
    assert code == (0 if err.startswith("imported") else 2), err[:500]
    if code == 2 and db.exists():  # refused by the store: nothing of the file was stored
        with open_store(f"sqlite:///{db}", create=False) as store:
            assert store.stats()["episodes"] == 0


@pytest.mark.parametrize("reader", sorted(READERS))
def test_every_reader_reads_its_valid_file(
    reader: str, labels: dict[str, bytes], tmp_path: Path
) -> None:
    name, read = READERS[reader]
    if reader == "model-meta":
        return  # a valid model is more than its metadata (tests/selection)
    path = tmp_path / name
    if name.endswith(".npz"):
        _write_npz(path, "header_json", _valid(reader, labels))
    else:
        path.write_bytes(_valid(reader, labels))
    assert read(path)


# --- the boundary itself


def test_lines_split_on_newline_only_and_are_numbered_exactly(tmp_path: Path) -> None:
    path = tmp_path / "x.jsonl"
    path.write_bytes('"a\u2028b"\n"\r\x85"\r\n\n"tail"'.encode())
    lines = list(textinput.read_lines(path))
    assert [line.text for line in lines] == ['"a\u2028b"', '"\r\x85"\r', "", '"tail"']
    assert [line.number for line in lines] == [1, 2, 3, 4]
    assert [line.complete for line in lines] == [True, True, True, False]
    path.write_bytes(b"ok\nbad \xff byte\nok\n")
    with pytest.raises(textinput.LineError, match=r"x.jsonl:2: not UTF-8 text \(byte 5"):
        list(textinput.read_lines(path))
    kept = list(textinput.read_lines(path, raise_errors=False))
    assert [line.problem is None for line in kept] == [True, False, True]


def test_an_over_long_line_is_refused_without_being_read_whole(tmp_path: Path) -> None:
    path = tmp_path / "x.jsonl"
    path.write_bytes(b"short\n" + b"z" * 5000 + b"\nafter\n")
    with pytest.raises(textinput.LineError, match=r"x.jsonl:2: line is longer than 1000 bytes"):
        list(textinput.read_lines(path, max_bytes=1000))
    kept = list(textinput.read_lines(path, max_bytes=1000, raise_errors=False))
    assert [(line.number, line.text, line.problem is None) for line in kept] == [
        (1, "short", True),
        (2, "", False),
        (3, "after", True),
    ]


@pytest.mark.parametrize(
    ("text", "problem"),
    [
        ("[" * 65 + "]" * 65, "nests more than 64 levels"),
        ("[" * 100_000, "nests more than 64 levels"),
        ('{"a": ' + "9" * 5000 + "}", "does not fit in 64 bits"),
        ('{"a": 9223372036854775808}', "does not fit in 64 bits"),
        ('{"a": "\\ud800"}', "unpaired surrogate"),
        ("{x", "not JSON (Expecting property name"),
    ],
)
def test_parse_json_names_the_problem_in_one_short_line(text: str, problem: str) -> None:
    with pytest.raises(textinput.LineError) as info:
        textinput.parse_json(text, "f.jsonl", 7)
    assert str(info.value).startswith("f.jsonl:7: ") and problem in str(info.value)
    assert len(str(info.value)) < 200


def test_parse_json_keeps_what_is_valid() -> None:
    deep_string = '"' + "[" * 500 + '"'  # brackets inside a string do not nest
    assert textinput.parse_json(deep_string, "f") == "[" * 500
    assert textinput.parse_json('{"a\u2028b": [-9223372036854775808]}', "f") == {
        "a\u2028b": [-(2**63)]
    }
    assert textinput.parse_json('"\\ud83d\\ude00"', "f") == "\U0001f600"  # a pair is text


def test_quote_is_short_whatever_the_value() -> None:
    assert len(textinput.quote("x" * 10**6)) < 120
    assert "digits" in textinput.quote(10**5000)
    assert len(textinput.quote([list(range(1000))] * 1000)) < 120
    assert textinput.quote("a\u2028b") == "'a\\u2028b'"


# --- the probes, through the command line: exit 2, one line, nothing written


def _snapshot(folder: Path) -> dict[str, str]:
    return {
        str(p): hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else "folder"
        for p in sorted(folder.rglob("*"))
    }


def _one_line(argv: list[str], folder: Path, capsys: pytest.CaptureFixture[str], *words: str):
    before = _snapshot(folder)
    capsys.readouterr()
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    lines = err.splitlines()
    assert len(lines) == 1 and ": error: " in lines[0], err[:500]
    assert "error: unexpected" not in lines[0], err[:500]
    assert len(lines[0]) < MAX_MESSAGE, lines[0][:300]
    for word in words:
        assert word in lines[0], lines[0]
    assert _snapshot(folder) == before
    return lines[0]


def _first_record(labels: dict[str, bytes]) -> dict:
    return json.loads(labels["jsonl"].split(b"\n")[1])


def _labels_file(folder: Path, *records: dict | str) -> Path:
    path = folder / "in.jsonl"
    body = [r if isinstance(r, str) else json.dumps(r, ensure_ascii=False) for r in records]
    path.write_text("\n".join([HEADER, *body]) + "\n", encoding="utf-8")
    return path


def _import(path: Path, folder: Path) -> list[str]:
    return ["labels", "import", str(path), "--db", f"sqlite:///{folder / 'k.db'}"]


@pytest.fixture
def workdir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("KNOTLAB_DB_URL", raising=False)
    monkeypatch.delenv(cli.DEBUG_ENV, raising=False)
    return tmp_path


def test_a_huge_line_is_refused_without_being_echoed(workdir: Path, capsys) -> None:
    path = workdir / "in.jsonl"
    with open(path, "wb") as fh:  # a 17 MB line: over the 16 MiB bound
        fh.write(HEADER.encode() + b'\n{"execution_id": "')
        fh.write(b"a" * (17 * 2**20))
        fh.write(b'"}\n')
    _one_line(_import(path, workdir), workdir, capsys, "line 2", "longer than 16777216 bytes")


@pytest.mark.parametrize("fmt", ["jsonl", "csv"])
def test_deep_nesting_is_refused_before_json_loads(workdir, capsys, labels, fmt) -> None:
    if fmt == "jsonl":
        path = _labels_file(workdir, "[" * 200_000 + "]" * 200_000)
        where = "line 2, field '(line)'"
    else:
        rows = list(csv.reader(io.StringIO(labels["csv"].decode())))
        rows[1][rows[0].index("metadata")] = "[" * 5000 + "]" * 5000
        path = workdir / "in.csv"
        with open(path, "w", newline="") as fh:
            csv.writer(fh, lineterminator="\n").writerows(rows)
        where = "line 2, field 'metadata'"
    _one_line(_import(path, workdir), workdir, capsys, where, "nests more than 64 levels")


@pytest.mark.parametrize(
    ("value", "problem"),
    [
        ("9" * 5000, "(5000 characters) does not fit in 64 bits"),
        (str(10**30), "does not fit in 64 bits"),
    ],
)
def test_a_huge_integer_in_metadata_is_refused(workdir, capsys, labels, value, problem) -> None:
    line = json.dumps(_first_record(labels)).replace('"metadata":{', f'"metadata":{{"n":{value},')
    line = line.replace('"metadata": {', f'"metadata": {{"n": {value}, ')
    assert value in line
    _one_line(_import(_labels_file(workdir, line), workdir), workdir, capsys, "line 2", problem)


def test_a_seed_outside_32_bits_is_refused_with_its_line(workdir, capsys, labels) -> None:
    record = _first_record(labels)
    record["steps"][0]["state_seed"] = 2**40
    path = _labels_file(workdir, record)
    _one_line(_import(path, workdir), workdir, capsys, "line 2", "state_seed", "32-bit")


@pytest.mark.parametrize(
    ("when", "problem"),
    [
        ("9999-12-31T23:59:59-05:00", "out of range"),
        ("0001-01-01T00:00:00+05:00", "out of range"),
        ("2026-13-01T00:00:00+00:00", "month must be in 1..12"),
        ("2026-01-01T00:00:00", "no UTC offset"),
    ],
)
def test_an_out_of_range_date_is_refused_clearly(workdir, capsys, labels, when, problem) -> None:
    record = _first_record(labels)
    record["started_at"] = when
    path = _labels_file(workdir, record)
    _one_line(_import(path, workdir), workdir, capsys, "line 2, field 'started_at'", problem)


@pytest.mark.parametrize("fmt", ["jsonl", "csv"])
def test_a_bad_byte_is_reported_on_its_own_line(workdir, capsys, labels, fmt) -> None:
    rows = labels[fmt].split(b"\n")
    rows[1] = rows[1][:20] + b"\xff" + rows[1][20:]
    path = workdir / f"in.{fmt}"
    path.write_bytes(b"\n".join(rows))
    _one_line(_import(path, workdir), workdir, capsys, "line 2", "not UTF-8 text")


def test_a_raw_u2028_inside_a_json_string_is_not_a_line_break(workdir, capsys, labels) -> None:
    record = _first_record(labels)
    record["labeller"] = "ann\u2028\u2029\x85e"
    path = _labels_file(workdir, record)
    assert "\u2028" in path.read_text(encoding="utf-8")
    assert cli.main(_import(path, workdir)) == 0
    out = workdir / "out.jsonl"
    url = f"sqlite:///{workdir / 'k.db'}"
    assert cli.main(["labels", "export", "--db", url, "--out", str(out)]) == 0
    assert json.loads(out.read_text(encoding="utf-8").split("\n")[1])["labeller"] == (
        "ann\u2028\u2029\x85e"
    )


def test_a_long_value_is_quoted_short(workdir, capsys, labels) -> None:
    record = _first_record(labels)
    record["status"] = "s" * 100_000
    line = _one_line(_import(_labels_file(workdir, record), workdir), workdir, capsys, "status")
    assert "(100000 characters)" in line


@pytest.mark.parametrize(
    ("content", "problem"),
    [
        ("[" * 100_000 + "\n", "nests more than 64 levels"),
        (TRIES_LINE.replace('"step_index": 0', '"step_index": 1e400') + "\n", "'step_index' is"),
        (TRIES_LINE.replace('"stage": 1', '"stage": ' + "7" * 5000) + "\n", "64 bits"),
        (TRIES_LINE + "\n\udcff\n", "tries.jsonl:2: not UTF-8"),  # a raw 0xff byte
    ],
)
def test_a_bad_tries_file_is_refused_in_one_line(workdir, capsys, labels, content, problem):
    (workdir / "labels.jsonl").write_bytes(labels["jsonl"])
    tries = workdir / "tries.jsonl"
    tries.write_bytes(content.encode("utf-8", "surrogateescape"))
    argv = ["labels", "tries", "--labels", "labels.jsonl", "--out", str(tries), "--force"]
    _one_line(argv, workdir, capsys, "tries.jsonl:", problem)


@pytest.mark.parametrize(
    ("payload", "problem"),
    [
        (b"[" * 100_000, "nests more than 64 levels"),
        (b'{"n": ' + b"1" * 5000 + b"}", "64 bits"),
        (b'{"a": "\xff"}', "not UTF-8"),
    ],
)
def test_a_bad_npz_header_is_refused_in_one_line(workdir, capsys, payload, problem) -> None:
    _write_npz(workdir / "lib.npz", "header_json", payload)
    _one_line(["demos", "info", "lib.npz"], workdir, capsys, "lib.npz", problem)


def test_a_bad_outcome_line_is_refused_or_skipped_in_one_line(tmp_path: Path, caplog) -> None:
    path = tmp_path / "outcomes.jsonl"
    path.write_bytes((OUTCOME_LINE + "\n").encode() + b"[" * 100_000 + b"\n\xff\n")
    with pytest.raises(KnotlabError, match=r"outcomes.jsonl:2: not a knotlab bench outcome line"):
        OutcomeLog(path).load(strict=True)
    assert list(OutcomeLog(path).load()) == [("nn", "t-0")]  # the others skipped, with warnings
    assert sum("ignoring an unreadable line" in r.message for r in caplog.records) == 2


@pytest.mark.parametrize(
    ("value", "expected"), [(3, 3), (3.0, 3), ("12", 12), (" -4 ", -4), (np.int64(7), 7)]
)
def test_a_form_fields_whole_number_is_read_as_typed(value, expected) -> None:
    assert textinput.whole_number(value, "a task number") == expected


@pytest.mark.parametrize(
    ("value", "said"),
    [
        (None, "type a task number"),
        ("  ", "type a task number"),
        (1.5, "must be a whole number, got 1.5"),
        ("abc", "must be a whole number, got 'abc'"),
        (float("nan"), "must be a whole number"),
        (True, "must be a whole number"),
        ("9" * 30, "does not fit in 64 bits"),
    ],
)
def test_a_form_fields_bad_number_is_one_line_naming_it(value, said) -> None:
    with pytest.raises(KnotlabError, match=said) as info:
        textinput.whole_number(value, "a task number")
    assert "\n" not in str(info.value)

"""Labels as files: export a store's executions to JSONL or CSV and import them back, validated.

JSONL: a header line ``{"format": "knotlab-labels", "version": 1}``, then one execution per line.
CSV: one ``execution`` row per execution followed by its ``step`` and ``dead_end`` rows; arrays,
lists and metadata are JSON text in their cells; an empty cell is null.
Export then import then export gives byte-identical files (values are stored as float32, and a
float32 printed with ``repr`` as a float64 reads back to the same float32).
An execution of a task other than the overhand knot names it: a ``task`` key in JSONL, a last
``task`` column in CSV (written only when some execution needs it); without it, labels are the
overhand knot's, so files from before tasks existed are unchanged. A file holds one task's labels,
and is refused by a store holding another task's (:class:`TaskMismatchError`).
An import reads and validates every row before writing anything, and writes in one transaction:
a bad row raises :class:`ImportRowError` naming the file, line and field, and nothing is stored.
"""

from __future__ import annotations

import csv
import json
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any, Literal, TextIO

import numpy as np

from knotlab.core.errors import InvalidInputError
from knotlab.core.outcomes import StepOutcome
from knotlab.core.selection.labels import OUTCOMES, DeadEndState, LabelledExecution, LabelledStep
from knotlab.core.tasks import DEFAULT_TASK
from knotlab.core.textinput import (
    MAX_LINE_BYTES,
    Line,
    LineError,
    parse_int,
    parse_json,
    parse_time,
    quote,
    read_lines,
)
from knotlab.labeling_db.errors import (
    ConflictError,
    ImportRowError,
    InvalidRecordError,
    TaskMismatchError,
)
from knotlab.labeling_db.models import EPISODE_STATUSES
from knotlab.labeling_db.store import StateProvenance, Store, StoredExecution

Format = Literal["jsonl", "csv"]
FORMAT_NAME = "knotlab-labels"
FORMAT_VERSION = 1
CSV_COLUMNS: tuple[str, ...] = (
    "row_type",
    "execution_id",
    "source",
    "labeller",
    "status",
    "task_id",
    "library_hash",
    "ended_in_knot",
    "metadata",
    "started_at",
    "finished_at",
    "index",
    "chosen_demo",
    "outcome",
    "candidates",
    "candidate_scores",
    "model_version",
    "labelled_at",
    "cloud_n3",
    "rope_nodes_k3",
    "state_task_id",
    "state_episode_step",
    "state_seed",
)
_EXEC_FIELDS = CSV_COLUMNS[1:11]
_STEP_FIELDS = CSV_COLUMNS[11:]
CSV_TASK_COLUMNS: tuple[str, ...] = (*CSV_COLUMNS, "task")  # when an execution is not overhand
MAX_NAME_CHARS = 200  # ids, names and keys: the store's key columns are String(200)
SEED_RANGE = (-(2**31), 2**31)  # a state's seed is a 32-bit integer in the store


def _task_of(item: StoredExecution) -> str | None:
    """The task an export names: None for the overhand knot's (and unknown) executions."""
    return None if item.task in (None, DEFAULT_TASK) else item.task


def _dumps(value: Any) -> str:
    return json.dumps(value, sort_keys=True, separators=(",", ":"), allow_nan=False)


def _iso(ts: datetime | None) -> str | None:
    return None if ts is None else ts.isoformat()


def _arr(a: np.ndarray | None) -> list[Any] | None:
    return None if a is None else np.asarray(a, dtype=float).tolist()


def execution_to_dict(item: StoredExecution) -> dict[str, Any]:
    """The JSON-ready form of one stored execution (the JSONL line, before encoding)."""
    ex = item.execution
    steps = []
    for i, step in enumerate(ex.steps):
        prov = item.step_provenance[i] if item.step_provenance else StateProvenance()
        steps.append(
            {
                "step_index": step.step_index,
                "chosen_demo": step.chosen_demo,
                "outcome": step.outcome.value,
                "candidates": list(step.candidates),
                "candidate_scores": _arr(step.candidate_scores_c),
                "model_version": step.model_version,
                "labelled_at": _iso(item.labelled_at[i]) if item.labelled_at else None,
                "cloud_n3": _arr(step.cloud_n3),
                "rope_nodes_k3": _arr(step.rope_nodes_k3),
                "state_task_id": prov.task_id,
                "state_episode_step": prov.episode_step,
                "state_seed": prov.seed,
            }
        )
    dead = []
    for i, de in enumerate(ex.dead_ends):
        prov = item.dead_end_provenance[i] if item.dead_end_provenance else StateProvenance()
        dead.append(
            {
                "cloud_n3": _arr(de.cloud_n3),
                "rope_nodes_k3": _arr(de.rope_nodes_k3),
                "state_task_id": prov.task_id,
                "state_episode_step": prov.episode_step,
                "state_seed": prov.seed,
            }
        )
    out: dict[str, Any] = {
        "execution_id": ex.execution_id,
        "source": ex.source,
        "labeller": ex.labeller,
        "status": item.status,
        "task_id": ex.task_id,
        "library_hash": ex.library_hash,
        "ended_in_knot": ex.ended_in_knot,
        "metadata": ex.metadata,
        "started_at": _iso(item.started_at),
        "finished_at": _iso(item.finished_at),
        "steps": steps,
        "dead_ends": dead,
    }
    if _task_of(item) is not None:
        out["task"] = item.task
    return out


def write_labels(items: list[StoredExecution], out: TextIO, fmt: Format) -> None:
    """Write executions to `out` as JSONL or CSV."""
    if fmt == "jsonl":
        out.write(_dumps({"format": FORMAT_NAME, "version": FORMAT_VERSION}) + "\n")
        for item in items:
            out.write(_dumps(execution_to_dict(item)) + "\n")
        return
    if fmt != "csv":
        raise InvalidRecordError(f"format must be 'jsonl' or 'csv', got {fmt!r}")
    writer = csv.writer(out, lineterminator="\n")
    with_task = any(_task_of(item) is not None for item in items)
    writer.writerow(CSV_TASK_COLUMNS if with_task else CSV_COLUMNS)
    tail = [""] if with_task else []

    def cell(v: Any) -> str:
        if v is None:
            return ""
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, str | int):
            return str(v)
        return _dumps(v)

    for item in items:
        d = execution_to_dict(item)
        task = [cell(d.get("task", DEFAULT_TASK))] if with_task else []
        writer.writerow(["execution", *(cell(d[c]) for c in _EXEC_FIELDS), *[""] * 12, *task])
        for step in d["steps"]:
            vals = {**step, "index": step["step_index"]}
            writer.writerow(
                [
                    "step",
                    d["execution_id"],
                    *[""] * 9,
                    *(cell(vals[c]) for c in _STEP_FIELDS),
                    *tail,
                ]
            )
        for i, de in enumerate(d["dead_ends"]):
            vals = {c: None for c in _STEP_FIELDS} | de | {"index": i}
            writer.writerow(
                [
                    "dead_end",
                    d["execution_id"],
                    *[""] * 9,
                    *(cell(vals[c]) for c in _STEP_FIELDS),
                    *tail,
                ]
            )


def export_labels(store: Store, out: TextIO, fmt: Format, *, source: str | None = None) -> int:
    """Write every execution in `store` (optionally of one source); returns how many."""
    items = store.stored_executions(source=source)
    write_labels(items, out, fmt)
    return len(items)


# ----------------------------------------------------------------------------- reading


@dataclass
class _Row:
    """A field getter for one input row that reports errors with file, line and field."""

    path: str
    line: int
    data: dict[str, Any]
    prefix: str = ""

    def fail(self, name: str, problem: str) -> ImportRowError:
        field = (self.prefix + name).rstrip(".") or "(row)"
        return ImportRowError(self.path, self.line, field, problem)

    def get(self, name: str, kind: str, *, optional: bool = False) -> Any:
        if name not in self.data:
            raise self.fail(name, "missing")
        v = self.data[name]
        if v is None:
            if optional:
                return None
            raise self.fail(name, "must not be null")
        if kind == "str":
            if not _is_name(v):
                raise self.fail(
                    name,
                    f"expected a non-empty string of at most {MAX_NAME_CHARS} characters without "
                    f"NUL, got {quote(v)}",
                )
        elif kind == "int":
            if isinstance(v, bool) or not isinstance(v, int):
                raise self.fail(name, f"expected an integer, got {quote(v)}")
        elif kind == "bool":
            if not isinstance(v, bool):
                raise self.fail(name, f"expected true or false, got {quote(v)}")
        elif kind == "time":
            try:
                return parse_time(v)
            except InvalidInputError as exc:
                raise self.fail(name, str(exc)) from None
        elif kind == "dict":
            if not isinstance(v, dict):
                raise self.fail(name, f"expected a JSON object, got {type(v).__name__}")
            try:
                json.dumps(v, allow_nan=False)
            except ValueError:
                raise self.fail(name, "contains NaN or infinite numbers") from None
        elif kind == "strlist":
            if not isinstance(v, list) or not all(_is_name(x) for x in v):
                raise self.fail(
                    name, f"expected a list of non-empty strings of at most {MAX_NAME_CHARS} chars"
                )
        elif kind == "vector":
            return self._array(name, v, 1)
        elif kind == "cloud":
            return self._array(name, v, 2)
        return v

    def _array(self, name: str, v: Any, ndim: int) -> np.ndarray:
        try:
            a = np.array(v)
        except (TypeError, ValueError):  # ragged lists
            a = None
        # strings, booleans and objects are not numbers
        a = a.astype(float) if a is not None and a.dtype.kind in "iuf" else None
        if a is None or a.ndim != ndim or (ndim == 2 and (a.shape[1] != 3 or a.shape[0] < 1)):
            want = "a list of numbers" if ndim == 1 else "a non-empty list of [x, y, z] rows"
            raise self.fail(name, f"expected {want}")
        if not np.all(np.isfinite(a)):
            raise self.fail(name, "contains NaN or infinite values")
        return a

    def enum(self, name: str, allowed: tuple[str, ...]) -> str:
        v = self.get(name, "str")
        if v not in allowed:
            raise self.fail(name, f"must be one of {allowed}, got {quote(v)}")
        return v


def _is_name(v: object) -> bool:
    return isinstance(v, str) and 0 < len(v) <= MAX_NAME_CHARS and "\x00" not in v


def _parse_step(row: _Row, i: int) -> tuple[LabelledStep, datetime | None, StateProvenance]:
    index = row.get("step_index", "int")
    if index != i:
        raise row.fail("step_index", f"expected {i} (steps must be in order), got {index}")
    try:
        step = LabelledStep(
            step_index=index,
            cloud_n3=row.get("cloud_n3", "cloud"),
            chosen_demo=row.get("chosen_demo", "str"),
            outcome=StepOutcome(row.enum("outcome", OUTCOMES)),
            rope_nodes_k3=row.get("rope_nodes_k3", "cloud", optional=True),
            candidates=tuple(row.get("candidates", "strlist")),
            candidate_scores_c=row.get("candidate_scores", "vector", optional=True),
            model_version=row.get("model_version", "str", optional=True),
        )
    except ImportRowError:
        raise
    except InvalidInputError as exc:
        raise row.fail("", str(exc)) from exc
    return step, row.get("labelled_at", "time", optional=True), _provenance(row)


def _provenance(row: _Row) -> StateProvenance:
    seed = row.get("state_seed", "int", optional=True)
    if seed is not None and not SEED_RANGE[0] <= seed < SEED_RANGE[1]:
        raise row.fail("state_seed", f"expected a 32-bit integer, got {quote(seed)}")
    return StateProvenance(
        row.get("state_task_id", "str", optional=True),
        row.get("state_episode_step", "int", optional=True),
        seed,
    )


def _parse_dead_end(row: _Row) -> tuple[DeadEndState, StateProvenance]:
    try:
        de = DeadEndState(
            row.get("cloud_n3", "cloud"), row.get("rope_nodes_k3", "cloud", optional=True)
        )
    except ImportRowError:
        raise
    except InvalidInputError as exc:
        raise row.fail("", str(exc)) from exc
    return de, _provenance(row)


def _build(
    row: _Row,
    steps: list[tuple[LabelledStep, datetime | None, StateProvenance]],
    dead: list[tuple[DeadEndState, StateProvenance]],
) -> StoredExecution:
    times = [t for _, t, _ in steps]
    if any(t is None for t in times) and not all(t is None for t in times):
        raise row.fail("labelled_at", "give a time for every step or for none")
    try:
        execution = LabelledExecution(
            execution_id=row.get("execution_id", "str"),
            source=row.enum("source", ("oracle", "human")),
            labeller=row.get("labeller", "str"),
            steps=tuple(s for s, _, _ in steps),
            ended_in_knot=row.get("ended_in_knot", "bool"),
            dead_ends=tuple(d for d, _ in dead),
            task_id=row.get("task_id", "str", optional=True),
            library_hash=row.get("library_hash", "str", optional=True),
            metadata=row.get("metadata", "dict"),
        )
        # absent (or an empty CSV cell): the overhand knot's, as every file before tasks
        task = row.get("task", "str", optional=True) if "task" in row.data else None
        return StoredExecution(
            execution,
            status=row.enum("status", EPISODE_STATUSES),
            started_at=row.get("started_at", "time"),
            finished_at=row.get("finished_at", "time", optional=True),
            labelled_at=tuple(times) if times and times[0] is not None else (),
            step_provenance=tuple(p for _, _, p in steps),
            dead_end_provenance=tuple(p for _, p in dead),
            task=task or DEFAULT_TASK,
        )
    except (InvalidInputError, InvalidRecordError) as exc:
        if isinstance(exc, ImportRowError):
            raise
        raise row.fail("", str(exc)) from exc


def _read_jsonl(lines: Iterable[Line], path: str) -> Iterator[tuple[int, StoredExecution]]:
    it = iter(lines)
    first = next(it, None)
    if first is None:
        raise ImportRowError(path, 1, "format", "file is empty (expected a knotlab-labels header)")
    try:
        header = parse_json(first.text, path, 1)
    except LineError as exc:
        raise ImportRowError(path, 1, "format", f"header is {exc.problem}") from None
    if not isinstance(header, dict) or header.get("format") != FORMAT_NAME:
        raise ImportRowError(path, 1, "format", f"expected {FORMAT_NAME!r} header")
    if header.get("version") != FORMAT_VERSION:
        raise ImportRowError(
            path, 1, "version", f"version {quote(header.get('version'))} is not {FORMAT_VERSION}"
        )
    for n, line, _, _ in it:
        if not line.strip():
            continue
        try:
            data = parse_json(line, path, n)
        except LineError as exc:
            raise ImportRowError(path, n, "(line)", exc.problem) from None
        if not isinstance(data, dict):
            raise ImportRowError(path, n, "(line)", "expected a JSON object")
        row = _Row(path, n, data)
        steps_raw = data.get("steps")
        if not isinstance(steps_raw, list):
            raise row.fail("steps", "expected a list")
        dead_raw = data.get("dead_ends")
        if not isinstance(dead_raw, list):
            raise row.fail("dead_ends", "expected a list")
        steps = []
        for i, s in enumerate(steps_raw):
            if not isinstance(s, dict):
                raise row.fail(f"steps[{i}]", "expected a JSON object")
            steps.append(_parse_step(_Row(path, n, s, f"steps[{i}]."), i))
        dead = []
        for i, d in enumerate(dead_raw):
            if not isinstance(d, dict):
                raise row.fail(f"dead_ends[{i}]", "expected a JSON object")
            dead.append(_parse_dead_end(_Row(path, n, d, f"dead_ends[{i}].")))
        yield n, _build(row, steps, dead)


_JSON_CELLS = {"metadata", "candidates", "candidate_scores", "cloud_n3", "rope_nodes_k3"}
_INT_CELLS = {"index", "state_episode_step", "state_seed"}


def _csv_row(path: str, line: int, raw: dict[str, str]) -> _Row:
    data: dict[str, Any] = {}
    for name, cell in raw.items():
        if cell == "":
            data[name] = None
        elif name in _JSON_CELLS:
            try:
                data[name] = parse_json(cell, path, line)
            except LineError as exc:
                raise ImportRowError(path, line, name, exc.problem) from None
        elif name in _INT_CELLS:
            try:
                data[name] = parse_int(cell, path, line)
            except LineError as exc:
                raise ImportRowError(path, line, name, exc.problem) from None
        elif name == "ended_in_knot":
            if cell not in ("true", "false"):
                raise ImportRowError(path, line, name, f"expected true or false, got {quote(cell)}")
            data[name] = cell == "true"
        else:
            data[name] = cell
    data["step_index"] = data.get("index")
    return _Row(path, line, data)


def _read_csv(lines: Iterable[Line], path: str) -> Iterator[tuple[int, StoredExecution]]:
    # Cells as long as the boundary's lines (a big cloud); the csv module's default is 128 kB.
    csv.field_size_limit(max(csv.field_size_limit(), MAX_LINE_BYTES))
    reader = csv.reader(line.text + "\n" if line.complete else line.text for line in lines)
    rows = _csv_rows(reader, path)
    try:
        header = next(rows)
    except StopIteration:
        raise ImportRowError(path, 1, "header", "file is empty (expected a header row)") from None
    columns = tuple(header)
    if columns not in (CSV_COLUMNS, CSV_TASK_COLUMNS):
        raise ImportRowError(
            path, 1, "header", f"expected the columns {', '.join(CSV_COLUMNS)}[, task]"
        )
    current: _Row | None = None
    steps: list[tuple[LabelledStep, datetime | None, StateProvenance]] = []
    dead: list[tuple[DeadEndState, StateProvenance]] = []
    for cells in rows:
        line = reader.line_num
        if not cells:
            continue
        if len(cells) != len(columns):
            raise ImportRowError(
                path, line, "(row)", f"has {len(cells)} cells, expected {len(columns)}"
            )
        row = _csv_row(path, line, dict(zip(columns, cells, strict=True)))
        kind = row.data["row_type"]
        if kind == "execution":
            if current is not None:
                yield current.line, _build(current, steps, dead)
            current, steps, dead = row, [], []
            continue
        if kind not in ("step", "dead_end"):
            raise row.fail("row_type", f"must be execution, step or dead_end, got {quote(kind)}")
        if current is None or row.data["execution_id"] != current.data["execution_id"]:
            raise row.fail("execution_id", "must follow the execution row it belongs to")
        if kind == "step":
            steps.append(_parse_step(row, len(steps)))
        else:
            if row.data["index"] != len(dead):
                raise row.fail("index", f"expected dead end {len(dead)}, got {row.data['index']}")
            dead.append(_parse_dead_end(row))
    if current is not None:
        yield current.line, _build(current, steps, dead)


def _csv_rows(reader: Any, path: str) -> Iterator[list[str]]:
    """The rows of a csv reader; its errors (a NUL, an over-long cell) name the line."""
    while True:
        try:
            row = next(reader)
        except StopIteration:
            return
        except csv.Error as exc:
            problem = f"not CSV ({quote(str(exc))})"
            raise ImportRowError(path, reader.line_num, "(row)", problem) from None
        yield row


def detect_format(path: str | Path) -> Format:
    """The format of a labels file from its extension (.jsonl or .csv)."""
    suffix = Path(path).suffix.lower()
    if suffix in (".jsonl", ".ndjson"):
        return "jsonl"
    if suffix == ".csv":
        return "csv"
    raise InvalidRecordError(f"{path}: cannot tell the format from {suffix!r}; use .jsonl or .csv")


def read_labels(path: str | Path, fmt: Format | None = None) -> list[StoredExecution]:
    """Read and validate a whole labels file; raises ImportRowError on the first bad row."""
    fmt = fmt or detect_format(path)
    if not Path(path).is_file():
        what = "is a folder, not a labels file" if Path(path).is_dir() else "labels file not found"
        raise FileNotFoundError(f"{path}: {what}")
    reader = _read_jsonl if fmt == "jsonl" else _read_csv
    items = []
    seen: dict[str, int] = {}
    try:  # lines split on "\n" only, bounded, decoded one at a time (core.textinput)
        for line, item in reader(read_lines(path), str(path)):
            key = item.execution.execution_id
            if key in seen:
                problem = f"{quote(key)} was already given on line {seen[key]}"
                raise ImportRowError(str(path), line, "execution_id", problem)
            seen[key] = line
            items.append(item)
    except LineError as exc:  # an over-long line, or one that is not UTF-8
        raise ImportRowError(str(path), exc.line or 1, "(line)", exc.problem) from None
    return items


def import_labels(
    store: Store,
    path: str | Path,
    fmt: Format | None = None,
    *,
    if_exists: str = "error",
    items: list[StoredExecution] | None = None,
) -> int:
    """Validate a labels file, then store all of it in one transaction; returns how many.

    ``items`` are the file's rows when already read with :func:`read_labels` (the command line
    reads the file before it opens, and maybe creates, the database).
    """
    items = read_labels(path, fmt) if items is None else items
    tasks = sorted({item.task or DEFAULT_TASK for item in items})
    if len(tasks) > 1:
        raise InvalidRecordError(
            f"{path}: holds labels of tasks {', '.join(map(repr, tasks))}; a labels file is one "
            "task's (nothing was imported)"
        )
    try:
        ids = store.add_executions(items, if_exists=if_exists, task=tasks[0] if tasks else None)
    except TaskMismatchError as exc:
        raise TaskMismatchError(f"{path}: {exc}") from exc
    except ConflictError as exc:
        raise ConflictError(f"{path}: {exc}") from exc
    return sum(i is not None for i in ids)

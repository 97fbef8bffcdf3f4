"""The store records the task of its labels (through their demo library) and refuses another's."""

from __future__ import annotations

import io
import json
from pathlib import Path

import pytest
from sqlalchemy import create_engine, text

from knotlab.labeling_db.errors import InvalidRecordError, TaskMismatchError
from knotlab.labeling_db.interchange import CSV_COLUMNS, export_labels, import_labels
from knotlab.labeling_db.store import StoredExecution, open_store, upgrade_database
from tests.db_fixtures import make_execution


def _export(url: str, fmt: str) -> str:
    out = io.StringIO()
    with open_store(url) as store:
        export_labels(store, out, fmt)  # type: ignore[arg-type]
    return out.getvalue()


def test_an_old_database_is_upgraded_to_the_overhand_knot(db_url: str) -> None:
    upgrade_database(db_url, revision="0002")
    engine = create_engine(db_url)
    with engine.begin() as conn:
        conn.execute(
            text("INSERT INTO demo_libraries (library_hash, created_at) VALUES ('old', :t)"),
            {"t": "2024-01-01 00:00:00"},
        )
    engine.dispose()
    with open_store(db_url) as store:
        assert store.tasks() == {"overhand"}
        store.check_task("overhand")
        with pytest.raises(TaskMismatchError, match=r"task 'overhand', not 'figure8'"):
            store.check_task("figure8")


def test_register_library_records_its_task_and_refuses_another(db_url: str) -> None:
    with open_store(db_url) as store:
        assert store.tasks() == set()
        store.check_task("figure8")  # a new store takes any task
        store.register_library("lib-8", name="fig", task="figure8")
        store.register_library("lib-8", task="figure8")  # again: fine
        assert store.tasks() == {"figure8"}
        with pytest.raises(TaskMismatchError) as err:
            store.register_library("lib-8")  # default: overhand
        msg = str(err.value)
        assert "\n" not in msg and "'figure8'" in msg and "'overhand'" in msg
        with pytest.raises(TaskMismatchError, match="holds labels of task 'figure8'"):
            store.check_task("overhand")
        assert err.value.exit_code == 2


def test_executions_take_their_library_task(db_url: str) -> None:
    with open_store(db_url) as store:
        store.register_library("lib-abc123", task="figure8")
        store.add_execution(make_execution("ex-1"))  # no task given: the library's
        (item,) = store.stored_executions()
        assert item.task == "figure8"
        with pytest.raises(TaskMismatchError, match="'figure8'"):
            store.add_executions([make_execution("ex-2")], task="overhand")
        with pytest.raises(TaskMismatchError, match="'figure8', not 'overhand'"):
            store.add_execution(StoredExecution(make_execution("ex-3"), task="overhand"))
        assert len(store.stored_executions()) == 1  # nothing was written


def test_a_task_other_than_overhand_needs_a_library() -> None:
    ex = make_execution("ex-1")
    bare = type(ex)(**{**ex.__dict__, "library_hash": None})
    with pytest.raises(InvalidRecordError, match="needs a library_hash"):
        StoredExecution(bare, task="figure8")
    StoredExecution(bare, task="overhand")


@pytest.mark.parametrize("fmt", ["jsonl", "csv"])
def test_overhand_exports_name_no_task(tmp_path: Path, fmt: str) -> None:
    url = f"sqlite:///{tmp_path / 'a.db'}"
    with open_store(url) as store:
        store.add_executions([make_execution(f"ex-{i}", seed=i) for i in range(2)])
    text_ = _export(url, fmt)
    if fmt == "jsonl":
        assert all("task" not in json.loads(line) for line in text_.splitlines()[1:])
    else:
        assert text_.splitlines()[0] == ",".join(CSV_COLUMNS)


@pytest.mark.parametrize("fmt", ["jsonl", "csv"])
def test_another_task_round_trips_and_is_refused_by_an_overhand_store(
    tmp_path: Path, fmt: str
) -> None:
    url = f"sqlite:///{tmp_path / 'a.db'}"
    with open_store(url) as store:
        store.register_library("lib-abc123", task="figure8")
        store.add_executions([make_execution(f"ex-{i}", seed=i) for i in range(2)])
    first = _export(url, fmt)
    if fmt == "jsonl":
        assert all(json.loads(line)["task"] == "figure8" for line in first.splitlines()[1:])
    else:
        assert first.splitlines()[0].endswith(",task")
    path = tmp_path / f"labels.{fmt}"
    path.write_text(first, encoding="utf-8")

    again = f"sqlite:///{tmp_path / 'b.db'}"
    with open_store(again) as store:
        assert import_labels(store, path) == 2
        assert store.tasks() == {"figure8"}
    assert _export(again, fmt) == first

    overhand = f"sqlite:///{tmp_path / 'c.db'}"
    with open_store(overhand) as store:
        store.register_library("lib-other")  # an overhand store
        with pytest.raises(TaskMismatchError) as err:
            import_labels(store, path)
        msg = str(err.value)
        assert "\n" not in msg and str(path) in msg and "'figure8'" in msg
        assert store.stored_executions() == []


def test_a_file_mixing_tasks_is_refused(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path / 'a.db'}"
    with open_store(url) as store:
        store.add_execution(make_execution("ex-0"))
    lines = _export(url, "jsonl").splitlines()
    other = json.loads(lines[1]) | {"execution_id": "ex-1", "task": "figure8"}
    path = tmp_path / "mixed.jsonl"
    path.write_text("\n".join([*lines, json.dumps(other)]) + "\n", encoding="utf-8")
    mixed = "holds labels of tasks 'figure8', 'overhand'"
    with (
        open_store(f"sqlite:///{tmp_path / 'b.db'}") as store,
        pytest.raises(InvalidRecordError, match=mixed),
    ):
        import_labels(store, path)

"""`knotlab db ...` and `knotlab labels export|import`: round trips and validated imports."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import pytest

from knotlab.app import cli
from knotlab.core.selection.labels import LabelledStep
from knotlab.labeling_db.store import open_store
from tests.db_fixtures import cloud, make_execution


def run(*argv: str) -> int:
    return cli.main(list(argv))


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def source_db(tmp_path_factory: pytest.TempPathFactory) -> str:
    """A database with oracle executions and human episodes in every status (read-only use)."""
    url = f"sqlite:///{tmp_path_factory.mktemp('source') / 'source.db'}"
    with open_store(url) as store:
        store.add_executions([make_execution(f"oracle-{i}", seed=i) for i in range(4)])
        store.add_execution(make_execution("no-steps", n_steps=0, knot=False, n_dead=2))
        store.add_start_states([cloud(i) for i in range(3)])
        for status in ("completed", "in_progress", "abandoned"):
            ep = store.start_episode("alice", task_id="t-7", library_hash="lib-abc123")
            store.add_label(ep.episode_id, LabelledStep(0, cloud(0), "s001-t0", "misgrasp"))
            store.add_label(ep.episode_id, LabelledStep(1, cloud(1), "s002-t1", "skipped"))
            if status != "in_progress":
                store.finish_episode(ep.episode_id, status=status)  # type: ignore[arg-type]
    return url


def test_db_init_upgrade_and_stats(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    url = f"sqlite:///{tmp_path / 'k.db'}"
    assert run("db", "upgrade", "--db", url) == 2
    assert "knotlab db init" in capsys.readouterr().err
    assert run("db", "init", "--db", url) == 0
    assert "created the knotlab schema at revision" in capsys.readouterr().out
    assert run("db", "init", "--db", url) == 0
    assert "already at the newest" in capsys.readouterr().out
    assert run("db", "upgrade", "--db", url) == 0
    assert run("db", "stats", "--db", url, "--json") == 0
    stats = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert stats["labels"] == 0 and stats["schema_revision"] == stats["schema_head"]
    assert run("db", "stats", "--db", f"sqlite:///{tmp_path / 'none.db'}") == 2
    assert "no such database" in capsys.readouterr().err
    assert not (tmp_path / "none.db").exists()


@pytest.mark.parametrize("fmt", ["jsonl", "csv"])
def test_export_import_export_is_identical(source_db: str, tmp_path: Path, fmt: str) -> None:
    first, second = tmp_path / f"a.{fmt}", tmp_path / f"b.{fmt}"
    target = f"sqlite:///{tmp_path / 'target.db'}"
    assert run("labels", "export", "--format", fmt, "--db", source_db, "--out", str(first)) == 0
    assert run("labels", "import", str(first), "--db", target) == 0
    assert run("labels", "export", "--format", fmt, "--db", target, "--out", str(second)) == 0
    assert first.read_bytes() == second.read_bytes()
    with open_store(source_db) as a, open_store(target) as b:
        assert a.stats()["labels"] == b.stats()["labels"] == 18
        assert b.stats()["episodes_by_status"] == {
            "abandoned": 1,
            "completed": 6,
            "in_progress": 1,
        }
        assert [e.execution_id for e in a.training_executions()] == [
            e.execution_id for e in b.training_executions()
        ]


def test_jsonl_and_csv_carry_the_same_data(source_db: str, tmp_path: Path) -> None:
    assert run("labels", "export", "--format", "csv", "--db", source_db,
               "--out", str(tmp_path / "x.csv")) == 0  # fmt: skip
    via_csv = f"sqlite:///{tmp_path / 'via_csv.db'}"
    assert run("labels", "import", str(tmp_path / "x.csv"), "--db", via_csv) == 0
    for url, name in ((source_db, "a.jsonl"), (via_csv, "b.jsonl")):
        assert run("labels", "export", "--db", url, "--out", str(tmp_path / name)) == 0
    assert (tmp_path / "a.jsonl").read_bytes() == (tmp_path / "b.jsonl").read_bytes()


def _edit_jsonl(path: Path, line_no: int, edit) -> None:
    lines = path.read_text().splitlines()
    data = json.loads(lines[line_no - 1])
    edit(data)
    lines[line_no - 1] = json.dumps(data)
    path.write_text("\n".join(lines) + "\n")


def _set(path: str, value):
    def edit(data: dict) -> None:
        *parents, last = path.split(".")
        node = data
        for p in parents:
            node = node[int(p)] if p.isdigit() else node[p]
        node[int(last) if last.isdigit() else last] = value

    return edit


JSONL_BAD_ROWS = [
    (3, _set("steps.1.outcome", "exploded"), "line 3, field 'steps[1].outcome'", "must be one of"),
    (4, _set("steps.0.cloud_n3", [[0.0, 1.0]]), "field 'steps[0].cloud_n3'", "[x, y, z] rows"),
    (2, _set("steps.2.cloud_n3.0.1", "1.5"), "field 'steps[2].cloud_n3'", "list of [x, y, z]"),
    (2, _set("steps.2.cloud_n3.0.1", float("nan")), "field 'steps[2].cloud_n3'", "NaN"),
    (3, _set("dead_ends.0.rope_nodes_k3", [[1, 2]]), "field 'dead_ends[0].rope_nodes_k3'", "rows"),
    (5, _set("steps.1.step_index", 7), "field 'steps[1].step_index'", "expected 1"),
    (2, _set("ended_in_knot", "yes"), "line 2, field 'ended_in_knot'", "true or false"),
    (3, _set("started_at", "yesterday"), "field 'started_at'", "ISO 8601"),
    (4, _set("labeller", ""), "field 'labeller'", "non-empty string"),
    (2, _set("execution_id", "oracle-2"), "line 4, field 'execution_id'", "already given"),
    (3, _set("steps.0.candidate_scores", [1.0]), "line 3", "candidate_scores_c must have"),
    (6, _set("steps", 5), "line 6, field 'steps'", "expected a list"),
    (2, _set("status", "done"), "field 'status'", "must be one of"),
]


@pytest.mark.parametrize(("line", "edit", "where", "problem"), JSONL_BAD_ROWS)
def test_a_malformed_jsonl_row_names_line_and_field_and_imports_nothing(
    source_db: str,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    line: int,
    edit,
    where: str,
    problem: str,
) -> None:
    path = tmp_path / "labels.jsonl"
    assert run("labels", "export", "--db", source_db, "--out", str(path)) == 0
    _edit_jsonl(path, line, edit)
    target_path = tmp_path / "target.db"
    target = f"sqlite:///{target_path}"
    with open_store(target) as store:
        store.add_execution(make_execution("already-here", seed=42))
    digest = _sha(target_path)
    capsys.readouterr()
    assert run("labels", "import", str(path), "--db", target) == 2
    err = capsys.readouterr().err
    assert where in err and problem in err and "nothing was imported" in err
    assert str(path) in err
    assert _sha(target_path) == digest
    with open_store(target) as store:
        assert [e.execution_id for e in store.training_executions()] == ["already-here"]


def test_malformed_csv_rows_and_files_are_refused(source_db: str, tmp_path: Path, capsys) -> None:
    path = tmp_path / "labels.csv"
    assert run("labels", "export", "--format", "csv", "--db", source_db, "--out", str(path)) == 0
    good = path.read_text().splitlines()
    target = f"sqlite:///{tmp_path / 'target.db'}"

    def swap(i: int, line: str) -> list[str]:
        return [*good[:i], line, *good[i + 1 :]]

    outcome_row = good[3].replace(",misgrasp,", ",melted,").replace(",progressed,", ",melted,")
    cases = [
        (["row_type,oops", *good[1:]], "line 1, field 'header'"),
        (swap(3, outcome_row), "line 4, field 'outcome'"),
        (swap(2, good[2].replace("step,", "stp,", 1)), "line 3, field 'row_type'"),
        (swap(2, good[2] + ",extra"), "line 3, field '(row)'"),
        ([good[0], *good[2:]], "line 2, field 'execution_id'"),  # a step without its execution
        (swap(2, good[2].replace("[[", "[[x", 1)), "line 3, field 'cloud_n3'"),
    ]
    for lines, where in cases:
        path.write_text("\n".join(lines) + "\n")
        capsys.readouterr()
        assert run("labels", "import", str(path), "--db", target) == 2
        err = capsys.readouterr().err
        assert where in err, err
    with open_store(target) as store:
        assert store.stats()["episodes"] == 0


def test_importing_an_execution_already_stored_changes_nothing(
    source_db: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "labels.jsonl"
    assert run("labels", "export", "--db", source_db, "--out", str(path)) == 0
    target = f"sqlite:///{tmp_path / 'target.db'}"
    with open_store(target) as store:
        store.add_execution(make_execution("oracle-3", seed=3))
    assert run("labels", "import", str(path), "--db", target) == 2
    assert "'oracle-3'" in capsys.readouterr().err
    with open_store(target) as store:
        assert store.stats()["episodes"] == 1
    assert run("labels", "import", str(path), "--db", target, "--if-exists", "skip") == 0
    with open_store(target) as store:
        assert store.stats()["episodes"] == 8


def test_export_format_follows_the_out_extension(source_db: str, tmp_path: Path) -> None:
    csv_path, jsonl_path = tmp_path / "x.csv", tmp_path / "x.jsonl"
    assert run("labels", "export", "--db", source_db, "--out", str(csv_path)) == 0
    assert csv_path.read_text().startswith("row_type,")  # CSV, not JSON lines in a .csv
    assert run("labels", "export", "--db", source_db, "--out", str(jsonl_path)) == 0
    assert json.loads(jsonl_path.read_text().splitlines()[0])["format"] == "knotlab-labels"
    explicit = tmp_path / "y.csv"
    assert (
        run("labels", "export", "--format", "csv", "--db", source_db, "--out", str(explicit)) == 0
    )
    assert explicit.read_bytes() == csv_path.read_bytes()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.csv", "x.jsonl", "y.csv"]


def test_db_and_labels_actions_are_wired_in_the_real_parser() -> None:
    from knotlab.app import cmd_db, cmd_labels

    parser = cli.build_parser()
    wired = {
        "db init": cmd_db._init,
        "db upgrade": cmd_db._upgrade,
        "db stats --json": cmd_db._stats,
        "labels export --format csv --source oracle --out x.csv": cmd_labels._export,
        "labels import x.jsonl --if-exists skip": cmd_labels._import,
    }
    for line, func in wired.items():
        args = parser.parse_args([*line.split(), "--db", "sqlite:///k.db"])
        assert args.func is func and args.db == "sqlite:///k.db", line
    args = parser.parse_args(["labels", "import", "x.csv", "--url", "sqlite:///old.db"])
    assert args.db == "sqlite:///old.db" and args.if_exists == "error" and args.format is None

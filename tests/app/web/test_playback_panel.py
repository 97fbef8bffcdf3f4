"""The playback panel's source list (no browser)."""

from __future__ import annotations


def test_playback_sources_list_table_i_first_main_level_first(tmp_path) -> None:
    from knotlab.app.web.playback_panel import results_dirs

    names = ("greedy_model_hard_main", "table1_hard", "table1_shared_main", "table1_main")
    for name in (*names, "table1_levels_main"):  # sorts before table1_main: still after it
        (tmp_path / name).mkdir()
        (tmp_path / name / "run.json").write_text('{"identity": {"seed": 0}}')
    (tmp_path / "not_a_run").mkdir()
    assert [p.rsplit("/", 1)[1] for p in results_dirs(tmp_path)] == [
        "table1_main",
        "table1_levels_main",
        "table1_shared_main",
        "greedy_model_hard_main",
        "table1_hard",
    ]


def test_playback_lists_only_the_apps_tasks_runs_at_any_depth_never_the_archive(tmp_path) -> None:
    """`knotlab app --task figure8` replays the figure-eight's runs (kept in results/figure8/),
    and the overhand app does not offer them."""
    import json

    from knotlab.app.web.playback_panel import results_dirs

    def run(path: str, task: str | None, **more: str) -> None:
        folder = tmp_path / path
        folder.mkdir(parents=True)
        identity = {"seed": 0, **({"task": task} if task else {}), **more}
        (folder / "run.json").write_text(json.dumps({"identity": identity}))

    run("table1_main", None)  # made before runs named their task: the overhand knot's
    run("figure8/table1_main", "figure8")
    run("figure8/transfer/greedy_shared", "figure8")
    run("archive/figure8_table1_main_5steps", "figure8")
    run("figure8/robustness/combined25", "figure8", world="combined25")
    run("figure8/robustness/tracker", "figure8", estimator="tracker")
    run("figure8/robustness/nominal", "figure8", world="nominal", estimator="perfect")
    (tmp_path / "figure8" / "broken").mkdir()
    (tmp_path / "figure8" / "broken" / "run.json").write_text("not json")
    names = [p.removeprefix(str(tmp_path) + "/") for p in results_dirs(tmp_path, "figure8")]
    assert names == [
        "figure8/table1_main",
        "figure8/robustness/nominal",
        "figure8/transfer/greedy_shared",
    ]
    assert [p.removeprefix(str(tmp_path) + "/") for p in results_dirs(tmp_path)] == ["table1_main"]


def test_the_default_episode_is_lookaheads_first_else_the_first_recorded(tmp_path) -> None:
    import json

    from knotlab.app.web.playback_panel import first_episode

    def outcomes(name: str, lines: list) -> str:
        (tmp_path / name).mkdir()
        text = "".join((x if isinstance(x, str) else json.dumps(x)) + "\n" for x in lines)
        (tmp_path / name / "outcomes.jsonl").write_text(text)
        return str(tmp_path / name)

    both = outcomes("both", [{"policy": "nn", "task_id": "t1"}, "{broken",
                             {"policy": "la2x5", "task_id": "t7"}])  # fmt: skip
    assert first_episode(both) == ("la2x5", "t7")
    no_search = outcomes("nn_only", [[1, 2], {"policy": "greedy", "task_id": "t3"}])
    assert first_episode(no_search) == ("greedy", "t3")
    assert first_episode(outcomes("empty", [])) is None
    assert first_episode(str(tmp_path / "missing")) is None

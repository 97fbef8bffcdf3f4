"""The playback panel's source list (no browser)."""

from __future__ import annotations


def test_playback_sources_list_table_i_first_main_level_first(tmp_path) -> None:
    from knotlab.app.web.playback_panel import results_dirs

    for name in ("greedy_model_hard_main", "table1_hard", "table1_shared_main", "table1_main"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "run.json").write_text("{}")
    (tmp_path / "not_a_run").mkdir()
    assert [p.rsplit("/", 1)[1] for p in results_dirs(tmp_path)] == [
        "table1_main",
        "table1_shared_main",
        "greedy_model_hard_main",
        "table1_hard",
    ]

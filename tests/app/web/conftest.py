"""Shared fixtures of the labelling-session tests: the shipped resources and a fresh store."""

from __future__ import annotations

import pytest

from knotlab.app import defaults
from knotlab.app.web.resources import load_resources
from knotlab.core.selection.qmodel import QModel
from knotlab.labeling_db.store import open_store


@pytest.fixture(scope="module")
def resources():
    """The shipped library and main training starts, ranked by the shipped model (per module:
    a test that switches models switches them back)."""
    res = load_resources(defaults.LIBRARY_PATH, defaults.task_set_path("main", "train"), 5)
    res.use(res.add_model(QModel.load(defaults.MODEL_PATH), "shipped").version)
    return res


@pytest.fixture
def store(tmp_path, resources):
    """A fresh SQLite store with the main training starts registered."""
    s = open_store(f"sqlite:///{tmp_path / 'k.db'}")
    resources.register_starts(s, "main")
    yield s
    s.close()

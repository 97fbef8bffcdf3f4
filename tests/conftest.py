"""Shared test set-up: the database fixtures as a plugin, and the project's root folder.

The test folders mirror core/'s stages (world, registration, demos, selection, experiments), the
storage layer (labeling_db) and the app (app). Shared builders live beside this file:
`tests/minilib.py` (a tiny real demo library, task sets and labels) and `tests/db_fixtures.py`
(SQLite and PostgreSQL stores).
"""

from __future__ import annotations

from pathlib import Path

import pytest

from knotlab.core.parallel import single_thread_blas

# One BLAS thread, as every knotlab command and `make test` run: a replay, a registration or a
# fit must give the numbers a command gives, also when pytest is started by hand.
single_thread_blas()

pytest.register_assert_rewrite("tests.db_fixtures", "tests.minilib")
pytest_plugins = ["tests.db_fixtures"]

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session")
def project_root() -> Path:
    """The repository root (where static/ and results/ live)."""
    return ROOT

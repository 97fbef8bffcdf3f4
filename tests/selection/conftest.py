"""Shared fixtures: the tiny real library (tests.minilib), its featurizer, transferer, a world."""

from __future__ import annotations

import pytest

from knotlab.core.registration.planner import DemoTransferer
from knotlab.core.selection.features import LibraryFeaturizer
from knotlab.core.world.sim import RopeWorld
from tests.minilib import mini_library


@pytest.fixture(scope="module")
def lib():
    return mini_library(2)


@pytest.fixture(scope="module")
def featurizer(lib):
    return LibraryFeaturizer(lib)


@pytest.fixture(scope="module")
def transferer(lib):
    return DemoTransferer(lib)


@pytest.fixture
def world():
    with RopeWorld() as w:
        yield w

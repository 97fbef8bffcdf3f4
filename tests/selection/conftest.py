"""Shared fixtures: the tiny real library (tests.minilib), an agent on it (its featurizer and
transferer), a world."""

from __future__ import annotations

import pytest

from knotlab.core.agent import Agent
from knotlab.core.world.sim import RopeWorld
from tests.minilib import mini_library


@pytest.fixture(scope="module")
def lib():
    return mini_library(2)


@pytest.fixture(scope="module")
def agent(lib):
    return Agent(lib)  # nearest neighbour


@pytest.fixture(scope="module")
def featurizer(agent):
    return agent.featurizer


@pytest.fixture(scope="module")
def transferer(agent):
    return agent.transferer


@pytest.fixture
def world():
    with RopeWorld() as w:
        yield w

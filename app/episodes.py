"""Stored labelling episodes as playback episodes (the CLI's `playback db:ID` and the app's tab)."""

from __future__ import annotations

from pathlib import Path

from knotlab.app import defaults
from knotlab.core.demos.library import DemoLibrary
from knotlab.core.errors import InvalidInputError
from knotlab.core.experiments.playback import (
    PlaybackEpisode,
    execution_episode,
    load_matching_library,
)
from knotlab.labeling_db.store import Store


def store_episode(
    store: Store, episode_id: int, library: str | Path | DemoLibrary | None = None
) -> tuple[PlaybackEpisode, DemoLibrary]:
    """Episode ``episode_id`` of the store, and the library it was labelled with: ``library``
    (a file, or the app's loaded library) when its hash matches, else the shipped default."""
    info = store.episode(episode_id)
    execution = next(
        (
            se.execution
            for se in store.stored_executions(labeller=info.labeller)
            if se.execution.execution_id == info.execution_id
        ),
        None,
    )
    if execution is None or not execution.steps:
        raise InvalidInputError(f"episode {episode_id} has no labelled steps to play")
    # The app places every state it shows at rest from an exactly kept rope; a replay of its
    # episodes does the same. An oracle's or imported episode ran on, and is replayed so.
    placed = store.placed_ropes(episode_id) if info.source == "human" else None
    episode = execution_episode(execution, f"{info.labeller}: episode {episode_id}", placed)
    if isinstance(library, DemoLibrary):
        if execution.library_hash in (None, library.content_hash()):
            return episode, library
        library = None  # labelled with another library: look for it as a file
    if execution.library_hash is None:
        return episode, DemoLibrary.load(library or defaults.LIBRARY_PATH)
    found = load_matching_library([library, defaults.LIBRARY_PATH], execution.library_hash)
    return episode, found

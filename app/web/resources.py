"""What every labelling tab shares: the library, the level's training starts, the ranking models.

Read-only after start-up except the model list, which grows when a retrain finishes; its lock
makes "switch to the new model" atomic for every tab.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from knotlab.core.agent import Agent
from knotlab.core.demos.library import DemoLibrary
from knotlab.core.demos.tasks import TaskSet
from knotlab.core.errors import InvalidInputError, KnotlabError
from knotlab.core.jsonsafe import json_safe
from knotlab.core.selection.agreement import OverlapPolicy
from knotlab.core.selection.features import LibraryFeaturizer
from knotlab.core.selection.qmodel import QModel
from knotlab.core.selection.scan_cache import ScanCacheIdentity, ScanSummaryCache
from knotlab.core.tasks import check_task_of, get_task
from knotlab.labeling_db.records import StateProvenance
from knotlab.labeling_db.store import Store, StoredExecution

SCAN_THREADS = 2  # threads of one interactive library scan


@dataclass(frozen=True, eq=False)
class RankingModel:
    """A model the app can rank with (None model: nearest neighbour) and its agent."""

    version: str | None  # content hash; None for nearest-neighbour ranking
    source: str  # "store", a file path, or "nearest neighbour"
    model: QModel | None
    agent: Agent

    @property
    def featurizer(self) -> LibraryFeaturizer:
        """The featurizer the model's features come from (its landmarks)."""
        return self.agent.featurizer

    @property
    def label(self) -> str:
        """How the GUI names it."""
        if self.model is None:
            return "nearest neighbour (no model)"
        # A file path is named by its file: the panel is narrow and the folder says nothing.
        source = Path(self.source).name if "/" in self.source else self.source
        return f"{self.version} ({source})"


def qmodel_from_store(store: Store, version: str | None = None) -> QModel:
    """Rebuild a stored model as a QModel (newest when version is None); hash checked."""
    record = store.load_model(version)
    info = record.info
    meta = {
        "format": "knotlab-qmodel",
        "version": int(info.params.get("format_version", 1)),
        "bias": info.params.get("bias"),
        "feature_spec": info.feature_spec,
        "hyperparameters": info.hyperparameters,
        "metrics": info.metrics,
        "hash": info.version,
    }
    return QModel.from_parts(dict(record.arrays), meta, f"{store.url} model {info.version}")


def save_qmodel_to_store(
    store: Store,
    model: QModel,
    library_hash: str,
    trained_on: Sequence[str],
    *,
    extra_metrics: Mapping[str, Any] | None = None,
) -> str:
    """Store a QModel under its content hash (no-op if already stored); returns the version.

    ``extra_metrics`` are stored beside the model's own (e.g. how it compared on held-out data).
    """
    version = model.content_hash()
    if any(m.version == version for m in store.list_models()):
        return version
    arrays, meta = model.to_parts()
    store.save_model(
        version,
        arrays=arrays,
        hyperparameters=meta["hyperparameters"],
        feature_spec=meta["feature_spec"],
        params={"bias": meta["bias"], "format_version": meta["version"]},
        # a metric with no data is NaN: strict JSON
        metrics=json_safe({**meta["metrics"], **(extra_metrics or {})}),
        library_hash=library_hash,
        trained_on=list(trained_on),
    )
    return version


# ----------------------------------------------------------------------------- seeding


@dataclass(frozen=True)
class SeedReport:
    """What seeding the store with the shipped model's training labels did, and how long."""

    path: Path | None  # the labels file; None when this installation does not have it
    added_executions: int
    added_labels: int
    present_executions: int
    seconds: float
    note: str = ""  # why nothing was seeded

    def describe(self) -> str:
        """One line for the start-up log."""
        if self.note:
            return self.note
        return (
            f"seeded the store with the shipped model's {self.added_executions} oracle-labelled "
            f"executions ({self.added_labels} labels) from {self.path} in {self.seconds:.1f} s"
        )


def _training_run(model: QModel) -> dict[str, Any]:
    """The model's recorded training run (its provenance), or {} for a model without one."""
    run = model.metrics.get("training_run") if isinstance(model.metrics, dict) else None
    return run if isinstance(run, dict) else {}


def shipped_labels_path(model: QModel, model_path: Path) -> Path | None:
    """The labels file the shipped model was trained on, as its provenance names it (a path
    relative to the repository it was trained in), if this installation has it."""
    from knotlab.app.defaults import REPO_DIR

    name = _training_run(model).get("labels")
    if not isinstance(name, str) or not name:
        return None
    named = Path(name)
    # Not the working directory: the app may be started anywhere.
    places = [named] if named.is_absolute() else [REPO_DIR / named, model_path.parent / named.name]
    return next((path for path in places if path.is_file()), None)


def shipped_training_executions(model: QModel, items: Sequence[StoredExecution]) -> list[str]:
    """The execution ids the model was fitted on: its recorded split of the labels file (the
    executions in file order); [] when the file is not the one it records."""
    from knotlab.core.selection.model_selection import split_executions

    run = _training_run(model)
    try:
        n, fraction, seed = (
            int(run["n_executions"]),
            float(run["validation_fraction"]),
            int(run["split_seed"]),
        )
    except (KeyError, TypeError, ValueError):
        return []
    if n != len(items):
        return []
    ids = [it.execution.execution_id for it in items]
    if run.get("refit_all"):
        return ids
    train_idx, _ = split_executions(n, fraction, seed)
    return [ids[i] for i in train_idx]


def seed_shipped_labels(
    store: Store, resources: AppResources, shipped: QModel, model_path: Path
) -> SeedReport:
    """Import the oracle labels the shipped model was trained on (once: ids already stored are
    skipped) and store the model itself with them, so a retrain adds human labels to them."""
    from knotlab.labeling_db.interchange import read_labels

    t0 = time.perf_counter()
    path = shipped_labels_path(shipped, model_path)
    if path is None:
        save_qmodel_to_store(store, shipped, resources.library_hash, [])
        named = _training_run(shipped).get("labels", "not recorded")
        return SeedReport(
            None,
            0,
            0,
            0,
            time.perf_counter() - t0,
            f"note: the labels the shipped model was trained on ({named}) are not in this "
            "installation; a retrain fits on the store's labels only",
        )
    items = read_labels(path)
    foreign = {it.execution.library_hash for it in items} - {None, resources.library_hash}
    if foreign:
        return SeedReport(
            path,
            0,
            0,
            0,
            time.perf_counter() - t0,
            f"note: {path} holds labels of library {sorted(foreign)[0]}, not this app's "
            f"{resources.library_hash}: not seeded",
        )
    result = store.seed_executions(items, task=resources.task.name)
    save_qmodel_to_store(
        store, shipped, resources.library_hash, shipped_training_executions(shipped, items)
    )
    return SeedReport(
        path,
        result.added_executions,
        result.added_labels,
        result.present_executions,
        time.perf_counter() - t0,
    )


class AppResources:
    """The library, the level's training starts, and the ranking models every tab can use."""

    def __init__(
        self,
        library: DemoLibrary,
        tasks: TaskSet,
        *,
        top_k: int = 5,
        overlap: float = 0.0,
        task: str | None = None,
    ) -> None:
        if top_k < 1:
            raise InvalidInputError(f"--top-k must be >= 1, got {top_k}")
        self.library = library
        self.library_hash = library.content_hash()
        self.tasks = tasks
        self.top_k = top_k
        # A seeded share of starts offered to a second labeller, for agreement statistics.
        self.overlap = OverlapPolicy(overlap, seed=0) if overlap > 0 else None
        # An expert waits on each scan: its chunks run on two threads (the kernel releases the
        # GIL; chunks are independent, so the costs are the same as on one).
        self.agent = Agent(library, None, "nn", task=task, top_k=top_k, scan_threads=SCAN_THREADS)
        self.task = self.agent.task
        self.transferer = self.agent.transferer
        self.registrar = self.agent.featurizer.registrar
        self._nn_featurizer = self.agent.featurizer
        self._lock = threading.Lock()
        self._models: dict[str, RankingModel] = {}
        self._current: RankingModel = RankingModel(None, "nearest neighbour", None, self.agent)
        # Library-scan summaries of start clouds, shared by every model (they do not depend on
        # one): what lets Suggest score all the starts in seconds.
        self.start_scans = ScanSummaryCache(ScanCacheIdentity.of(self._nn_featurizer))

    def load_start_scans(self, path: Path) -> str:
        """Take precomputed scan summaries from ``path`` if it fits this library; a line saying
        what happened (a missing or unfitting file is not an error: scans are then made live)."""
        if not path.exists():
            return f"no precomputed start scans ({path.name}): Suggest scans each start once"
        try:
            loaded = ScanSummaryCache.load(path, self.start_scans.identity)
        except (KnotlabError, OSError, ValueError) as exc:
            return f"precomputed start scans not used: {exc}"
        self.start_scans = loaded
        return f"{len(loaded)} precomputed start scans from {path.name}"

    # --- models
    def add_model(self, model: QModel, source: str) -> RankingModel:
        """Make a model available (refused when it does not fit the library); returns it."""
        ranking = RankingModel(model.content_hash(), source, model, self.agent.with_model(model))
        with self._lock:
            self._models.setdefault(ranking.version or "", ranking)
            return self._models[ranking.version or ""]

    def use(self, version: str | None) -> RankingModel:
        """Rank with model ``version`` from now on (None: nearest neighbour)."""
        with self._lock:
            if version is None:
                self._current = RankingModel(None, "nearest neighbour", None, self.agent)
            elif version not in self._models:
                raise InvalidInputError(f"no model {version!r} loaded in the app")
            else:
                self._current = self._models[version]
            return self._current

    @property
    def current(self) -> RankingModel:
        """The model new states are ranked by."""
        with self._lock:
            return self._current

    def models(self) -> list[RankingModel]:
        """Every loaded model, in the order they were added."""
        with self._lock:
            return list(self._models.values())

    def loaded(self, version: str | None) -> RankingModel | None:
        """The loaded model ``version`` (None: not loaded, or nearest neighbour)."""
        with self._lock:
            return None if version is None else self._models.get(version)

    def warm_up(self) -> None:
        """Prepare the library side of the scan (and compile the kernel) before a tab waits."""
        cloud = self.library[0].pre_cloud_n3
        for ranking in {id(r.featurizer): r for r in [self.current, *self.models()]}.values():
            ranking.featurizer.features(cloud) if ranking.model else ranking.featurizer.scan(cloud)

    # --- start states
    def register_starts(self, store: Store, level: str) -> int:
        """Queue the level's training starts in the store once; returns how many were added."""
        known = store.start_task_ids()
        todo = [t for t in self.tasks if t.task_id not in known]
        if not todo:
            return 0
        from knotlab.core.world.sim import RopeWorld

        clouds = []
        with RopeWorld() as world:  # the cloud a tab will observe, so step 0's label matches it
            for t in todo:
                world.reset(np.asarray(t.start_nodes_k3))
                clouds.append(self.agent.observe(world))
        store.register_library(self.library_hash, name=f"{level} library", task=self.task.name)
        store.add_start_states(
            clouds,
            rope_nodes_k3=[t.start_nodes_k3 for t in todo],
            provenance=[StateProvenance(t.task_id, 0, None) for t in todo],  # task id names it
        )
        return len(todo)


def load_resources(
    library_path: Path,
    tasks_path: Path,
    top_k: int,
    overlap: float = 0.0,
    task: str | None = None,
) -> AppResources:
    """Library and task set from files (the task set must be a training split)."""
    library = DemoLibrary.load(library_path)
    check_task_of("demo library", library.metadata.get("task"), get_task(task or library.task))
    tasks = TaskSet.load(tasks_path)
    if tasks.split != "train":
        raise InvalidInputError(
            f"{tasks_path}: the app labels training starts only, this task set is the "
            f"{tasks.split!r} split"
        )
    check_task_of("task set", tasks.metadata.get("task"), get_task(task or library.task))
    return AppResources(library, tasks, top_k=top_k, overlap=overlap, task=task)

"""The labelling app's server: one viser server, one LabelTab per connected browser tab.

Owns what tabs share: the store, the resources (library, starts, models) and the retrain job.
"""

from __future__ import annotations

import contextlib
import io
import logging
import threading
from pathlib import Path

import numpy as np
import viser

from knotlab.app.web.jobs import RetrainJob, RetrainReport
from knotlab.app.web.resources import AppResources, qmodel_from_store
from knotlab.app.web.sim_pool import SimPool
from knotlab.app.web.tab import LabelTab
from knotlab.labeling_db.store import Store

log = logging.getLogger(__name__)


class LabelApp:
    """The running app: viser server, tabs, store, models and retraining."""

    def __init__(
        self,
        store: Store,
        resources: AppResources,
        library_path: Path,
        *,
        host: str = "127.0.0.1",
        port: int = 8080,
        lite_rendering: bool = False,
        sim_workers: int = 2,
        test_tasks_path: Path | None = None,
    ) -> None:
        self.store = store
        self._test_tasks_path = test_tasks_path
        self._test_tasks = None
        self.resources = resources
        self.retrain_job = RetrainJob(store.url, str(library_path))
        # Tries run in worker processes (0: on the tab's own thread, e.g. for debugging).
        self.sim_pool = SimPool(str(library_path), sim_workers) if sim_workers > 0 else None
        self._retrain_text = ""
        self._retrain_fraction = 0.0
        self._tabs: dict[int, LabelTab] = {}
        self.suggested: list[int] = []  # start state ids, most informative first
        self.suggest_text = ""
        self._suggest_lock = threading.Lock()
        self._suggesting = False
        self._tabs_lock = threading.Lock()
        with contextlib.redirect_stdout(io.StringIO()):  # viser prints a banner even when quiet
            self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.server.gui.configure_theme(control_width="large", dark_mode=False)
        if lite_rendering:  # software WebGL (headless tests): no HDRI stall, no shadows
            self.server.scene.configure_environment_map(None)
            self.server.scene.configure_default_lights(True, cast_shadow=False)
        self.server.initial_camera.position = (0.0, -0.9, 0.8)
        self.server.initial_camera.look_at = (0.0, 0.0, 0.0)
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(self._disconnect)

    @property
    def url(self) -> str:
        """Where the app is served."""
        return f"http://{self.server.get_host()}:{self.server.get_port()}"

    def tabs(self) -> list[LabelTab]:
        """The connected tabs."""
        with self._tabs_lock:
            return list(self._tabs.values())

    def tab(self, client_id: int) -> LabelTab | None:
        """The tab of one client id."""
        with self._tabs_lock:
            return self._tabs.get(client_id)

    def _connect(self, client: viser.ClientHandle) -> None:
        tab = LabelTab(self, client)
        with self._tabs_lock:
            self._tabs[client.client_id] = tab
        tab.open()

    def _disconnect(self, client: viser.ClientHandle) -> None:
        with self._tabs_lock:
            tab = self._tabs.pop(client.client_id, None)
        if tab is not None:
            tab.close()

    def start_nodes(self, split: str, number: int) -> np.ndarray:
        """The start rope of training start or test task ``number`` (for Inspect)."""
        from knotlab.core.demos.tasks import TaskSet
        from knotlab.core.errors import InvalidInputError

        if split == "train":
            tasks = self.resources.tasks
        else:
            if self._test_tasks is None:
                if self._test_tasks_path is None:
                    raise InvalidInputError("this app was started without a test task set")
                self._test_tasks = TaskSet.load(self._test_tasks_path)
            tasks = self._test_tasks
        if not 0 <= number < len(tasks):
            raise InvalidInputError(f"{split} tasks are numbered 0-{len(tasks) - 1}, got {number}")
        return np.asarray(tasks[number].start_nodes_k3)

    def start_nodes_of(self, start: str) -> np.ndarray:
        """The start rope of a training task id, or of a stored start state "state:<id>"."""
        from knotlab.core.errors import InvalidInputError

        if start.startswith("state:"):
            state = self.store.get_state(int(start.split(":", 1)[1]))
            if state.rope_nodes_k3 is None:
                raise InvalidInputError(f"{start} has no rope nodes to simulate from")
            return np.asarray(state.rope_nodes_k3)
        for task in self.resources.tasks:
            if task.task_id == start:
                return np.asarray(task.start_nodes_k3)
        raise InvalidInputError(f"{start!r} is not a training start of this app's level")

    # ------------------------------------------------------------------ models
    def model_rows(self) -> list[tuple[str, str | None, str]]:
        """(dropdown label, version, table row) for every model the tabs can rank with."""
        stored = {m.version: m for m in self.store.list_models()}
        rows: list[tuple[str, str | None, str]] = [("nearest neighbour", None, "")]
        for ranking in self.resources.models():
            info = stored.get(ranking.version or "")
            m = ranking.model.metrics if ranking.model is not None else {}
            run = m.get("training_run", {}) if isinstance(m, dict) else {}
            val = run.get("validation", {}) if isinstance(run, dict) else {}
            if info is not None:
                when = info.created_at.strftime("%m-%d %H:%M")
                n = str(info.n_training_labels)
                val = {**val, **{k[4:]: v for k, v in info.metrics.items() if k.startswith("val_")}}
            else:  # a model file (the shipped default): its size is in its training run
                when, n = "file", str(m.get("n_states", "?")) + " states"
            top1 = val.get("top1")
            auc = val.get("value_auc")
            row = (
                f"| {(ranking.version or '')[:8]} | {when} | {n} | "
                f"{'-' if top1 is None else f'{top1:.3f}'} | "
                f"{'-' if auc is None else f'{auc:.3f}'} |"
            )
            rows.append((ranking.label, ranking.version, row))
        return rows

    def use_model(self, version: str | None) -> None:
        """Rank every tab's next state with ``version`` (None: nearest neighbour)."""
        self.resources.use(version)
        for tab in self.tabs():
            tab.refresh_models()

    # ------------------------------------------------------------------ retraining
    def retrain_state(self) -> tuple[bool, str, float]:
        """(running, stage text, fraction done) for the panels."""
        return self.retrain_job.running, self._retrain_text, self._retrain_fraction

    def start_retrain(self) -> bool:
        """Start a retrain on every label in the store; False when one is running."""
        started = self.retrain_job.start(self._on_retrain_report)
        if started:
            self._retrain_text, self._retrain_fraction = "starting the training process", 0.02
            self._broadcast_retrain()
        return started

    def _on_retrain_report(self, report: RetrainReport) -> None:
        self._retrain_text, self._retrain_fraction = report.text, report.fraction
        if report.kind == "done" and report.version is not None:
            try:
                model = qmodel_from_store(self.store, report.version)
                self.resources.add_model(model, "store")
                self.resources.use(report.version)
            except Exception as exc:
                report = RetrainReport("error", f"cannot load the new model: {exc}")
                self._retrain_text = report.text
        metrics = report.metrics
        if report.kind == "done":
            top1 = metrics.get("val_top1")
            summary = (
                f"{metrics.get('n_states')} states; validation top-1 "
                f"{'n/a' if top1 is None else f'{top1:.3f}'}; next states are ranked by it"
            )
            self._retrain_text = f"model {report.version}: {summary}"
        elif report.kind == "error":
            self._retrain_text = f"retrain failed (the old model stays): {report.text}"
        for tab in self.tabs():
            tab.show_retrain()
            if report.kind in ("done", "error"):
                tab.refresh_models()
                tab.notify(
                    "retrain finished" if report.kind == "done" else "retrain failed",
                    self._retrain_text,
                    "green" if report.kind == "done" else "red",
                )

    def _broadcast_retrain(self) -> None:
        for tab in self.tabs():
            tab.show_retrain()

    # ------------------------------------------------------------------ suggestions
    def start_suggest(self) -> bool:
        """Rank unlabelled starts by how much a label would teach the model, in the background."""
        ranking = self.resources.current
        with self._suggest_lock:
            if self._suggesting or ranking.model is None:
                return False
            self._suggesting = True

        def work() -> None:
            from knotlab.core.selection.acquisition import rank_for_labelling, score_scan

            try:
                states = self.store.start_states_to_label()
                keys = self.resources.library.keys
                scores = []
                for i, st in enumerate(states):
                    phi, scan = ranking.featurizer.features(st.cloud_n3)
                    assert ranking.model is not None
                    scores.append(score_scan(f"{st.state_id}", scan, phi, ranking.model, keys))
                    if i % 10 == 0:
                        self._suggest_progress(f"scoring {i + 1} of {len(states)} starts")
                order = rank_for_labelling(scores, by="combined", seed=0)
                self.suggested = [int(r.score.key) for r in order]
                by_id = {st.state_id: st for st in states}
                top = [
                    f"{r.rank}. `{by_id[int(r.score.key)].provenance.task_id}` "
                    f"(Q margin {r.score.margin:.3f}, NN/greedy disagree: "
                    f"{'yes' if r.score.disagreement else 'no'})"
                    for r in order[:5]
                ]
                text = f"{len(order)} starts ranked by {ranking.label}; first:  \n" + "  \n".join(
                    top
                )
            except Exception as exc:
                text = f"suggest failed: {type(exc).__name__}: {exc}"
            with self._suggest_lock:
                self._suggesting = False
            self._suggest_progress(text)

        threading.Thread(target=work, name="suggest", daemon=True).start()
        return True

    def _suggest_progress(self, text: str) -> None:
        self.suggest_text = text
        for tab in self.tabs():
            tab.show_suggest(text, self._suggesting)

    def stop(self) -> None:
        """Stop serving: close every tab (no half label), stop a retrain, stop viser."""
        for tab in self.tabs():
            tab.close()
        self.retrain_job.stop()
        with contextlib.redirect_stdout(io.StringIO()):
            self.server.stop()
        if self.sim_pool is not None:
            self.sim_pool.close()


def load_models(
    app_resources: AppResources, store: Store, model_arg: str | None, default_model: Path
) -> str:
    """Load the models the app can rank with and pick the current one; returns a description.

    ``model_arg`` is a model file or a stored version; without it the newest stored model is used,
    else the shipped default model, else nearest-neighbour ranking.
    """
    from knotlab.core.errors import InvalidInputError
    from knotlab.core.selection.qmodel import QModel

    notes = []
    stored_versions = [m.version for m in store.list_models()]
    for version in stored_versions:
        try:
            app_resources.add_model(qmodel_from_store(store, version), "store")
        except Exception as exc:  # a model of another library stays in the store, unused
            notes.append(f"stored model {version} skipped: {exc}")
    if default_model.exists():
        try:
            app_resources.add_model(QModel.load(default_model), str(default_model))
        except Exception as exc:
            notes.append(f"{default_model} skipped: {exc}")
    if model_arg is not None:
        path = Path(model_arg)
        if path.exists():
            chosen = app_resources.add_model(QModel.load(path), str(path))
        elif model_arg in {r.version for r in app_resources.models()}:
            chosen = app_resources.use(model_arg)
        else:
            raise InvalidInputError(
                f"--model {model_arg!r} is neither a model file nor a stored model version "
                f"(stored: {', '.join(stored_versions) or 'none'})"
            )
        app_resources.use(chosen.version)
    else:
        loaded = app_resources.models()
        newest_stored = [r for r in loaded if r.source == "store"]
        pick = newest_stored[-1] if newest_stored else (loaded[-1] if loaded else None)
        app_resources.use(None if pick is None else pick.version)
    for note in notes:
        log.warning(note)
    return app_resources.current.label

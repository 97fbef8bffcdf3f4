"""The labelling app's server: one viser server, one LabelTab per connected browser tab.

Owns what tabs share: the store, the resources (library, starts, models) and the retrain job.
"""

from __future__ import annotations

import contextlib
import io
import logging
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import viser

from knotlab.app.web.access import AccessGate
from knotlab.app.web.icons import warm_icon_cache_in_background
from knotlab.app.web.jobs import ReportKind, RetrainJob, RetrainOutcome, RetrainReport
from knotlab.app.web.prop_hints import cache_prop_hints_per_class
from knotlab.app.web.resources import (
    AppResources,
    RankingModel,
    qmodel_from_store,
    save_qmodel_to_store,
    seed_shipped_labels,
)
from knotlab.app.web.session_records import Phase
from knotlab.app.web.sim_pool import SimPool
from knotlab.app.web.tab import LabelTab, NotifyColour
from knotlab.labeling_db.store import LabelMix, Store

log = logging.getLogger(__name__)
SUGGEST_REPORT_S = 0.25  # s between Suggest's progress reports (a start takes 0.02-0.2 s)
REASON_CHARS = 200  # the store keeps an activation's reason in 200 characters


@dataclass(frozen=True)
class ModelRow:
    """One model as the Model tab lists it."""

    label: str  # the dropdown's name of it
    version: str | None  # None: nearest neighbour
    active: bool  # every tab's next state is ranked by it
    made: str
    labels: str  # labels it was trained on
    top1: float | None  # validation top-1 (a retrained one: on the held-out executions)
    value_auc: float | None


def _short(version: str | None) -> str:
    """A model as the one-line texts name it."""
    return "nearest neighbour" if version is None else version[:8]


def _finish_note(kind: ReportKind, *, refused: bool) -> tuple[str, NotifyColour]:
    """The title and colour of the notification that a retrain ended."""
    if kind is ReportKind.ERROR:
        return "retrain failed", "red"
    return ("new model kept inactive", "yellow") if refused else ("new model active", "green")


def _clip(reason: str) -> str:
    """A reason the store can keep."""
    return reason if len(reason) <= REASON_CHARS else reason[: REASON_CHARS - 3] + "..."


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
        token: str | None = None,
    ) -> None:
        warm_icon_cache_in_background()  # before any tab needs them
        self.store = store
        self.lite_rendering = lite_rendering  # every tab's scene drawn for software WebGL
        self.token = token  # None: no token asked (loopback)
        self._test_tasks_path = test_tasks_path
        self._test_tasks = None
        self.resources = resources
        self.retrain_job = RetrainJob(store.url, str(library_path))
        # Tries run in worker processes (0: on the tab's own thread, e.g. for debugging).
        self.sim_pool = SimPool(str(library_path), sim_workers) if sim_workers > 0 else None
        self._retrain_text = ""
        self._retrain_fraction = 0.0
        self.last_outcome: RetrainOutcome | None = None  # the last finished retrain
        self.pending: RetrainOutcome | None = None  # a new model kept inactive: "use it anyway"
        self._tabs: dict[int, LabelTab] = {}
        self._gone: set[int] = set()  # client ids that disconnected
        self.suggested: list[int] = []  # start state ids, most informative first
        self.suggest_text = ""
        self._suggest_lock = threading.Lock()
        self._suggesting = False
        self._suggest_cancel = threading.Event()
        self._suggest_fraction = 0.0
        self._tabs_lock = threading.Lock()
        cache_prop_hints_per_class()  # ~0.3 ms off each of a new state's 40-60 handles
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

    def labelling_tab(self, labeller: str, *, besides: LabelTab) -> LabelTab | None:
        """Another open tab in which ``labeller`` is labelling now (None: there is none)."""
        for tab in self.tabs():
            session = tab.session
            if (
                tab is not besides
                and not tab.closed
                and session is not None
                and session.labeller == labeller
                and session.phase is not Phase.CLOSED
            ):
                return tab
        return None

    def tab(self, client_id: int) -> LabelTab | None:
        """The tab of one client id."""
        with self._tabs_lock:
            return self._tabs.get(client_id)

    def _connect(self, client: viser.ClientHandle) -> None:
        if self.token is None:
            self._admit(client)
            return
        # Nothing of the app (scene, panels, state) goes to a browser before the token.
        AccessGate(client, self.token, lambda: self._admit(client)).open()

    def _admit(self, client: viser.ClientHandle) -> None:
        """Build the tab of a client that may use the app, and start it."""
        with self._tabs_lock:
            if client.client_id in self._gone:
                return  # it went away while the token was asked
        tab = LabelTab(self, client)
        with self._tabs_lock:
            self._tabs[client.client_id] = tab
        tab.open()

    def _disconnect(self, client: viser.ClientHandle) -> None:
        with self._tabs_lock:
            tab = self._tabs.pop(client.client_id, None)
            self._gone.add(client.client_id)
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
    def model_rows(self) -> list[ModelRow]:
        """Every model the tabs can rank with (nearest neighbour first), the active one marked."""
        stored = {m.version: m for m in self.store.list_models()}
        current = self.resources.current.version
        rows = [ModelRow("nearest neighbour", None, current is None, "-", "-", None, None)]
        for ranking in self.resources.models():
            info = stored.get(ranking.version or "")
            m = ranking.model.metrics if ranking.model is not None else {}
            run = m.get("training_run", {}) if isinstance(m, dict) else {}
            val = run.get("validation", {}) if isinstance(run, dict) else {}
            held = (info.metrics.get("held_out") if info is not None else None) or {}
            if isinstance(held.get("candidate"), dict):  # the retrain's own held-out scores
                val = held["candidate"]
            if info is not None and info.n_training_labels:
                n = str(info.n_training_labels)
            else:  # a model file (the shipped default): its size is in its training run
                n = str(m.get("n_states", "?")) + " states"
            # A model file (the shipped default) is stored too, but was made elsewhere.
            made = (
                info.created_at.strftime("%m-%d %H:%M")
                if info is not None and ranking.source == "store"
                else "file"
            )
            top1, auc = val.get("top1"), val.get("value_auc")
            rows.append(
                ModelRow(
                    ranking.label,
                    ranking.version,
                    ranking.version == current,
                    made,
                    n,
                    None if top1 is None else float(top1),
                    None if auc is None else float(auc),
                )
            )
        return rows

    def active_text(self) -> str:
        """What ranks every tab's next state, since when and why (the Model tab's first line)."""
        current = self.resources.current
        record = self.store.active_model()
        line = f"**Next states are ranked by** {current.label}"
        if record is not None and record.version == current.version:
            when = record.activated_at.astimezone().strftime("%m-%d %H:%M")
            line += f"  \nactive since {when}: {record.reason}"
        return line

    def use_model(self, version: str | None, *, reason: str) -> RankingModel:
        """Make ``version`` (None: nearest neighbour) the active model for every tab's next
        state, and persist it, so a restarted app ranks with it too."""
        from knotlab.core.errors import InvalidInputError

        ranking = self.resources.loaded(version)
        if version is not None and ranking is None:
            raise InvalidInputError(f"no model {version!r} loaded in the app")
        if ranking is not None and ranking.model is not None:  # a model file: stored first
            save_qmodel_to_store(self.store, ranking.model, self.resources.library_hash, [])
        self.store.set_active_model(version, reason=_clip(reason))
        chosen = self.resources.use(version)
        if self.pending is not None and self.pending.version == version:
            self.pending = None
            self._retrain_text = f"model {_short(version)} activated: {reason}"
        for tab in self.tabs():
            tab.refresh_models()
            tab.show_retrain()
        return chosen

    # ------------------------------------------------------------------ labels
    def label_mix(self) -> LabelMix:
        """The labels a retrain would fit on, per source and labeller."""
        return self.store.label_mix()

    def labels_changed(self) -> None:
        """Labels were stored or removed: every tab's retrain panel shows the new mix."""
        mix = self.label_mix()
        for tab in self.tabs():
            tab.show_label_mix(mix)

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
        if report.kind is ReportKind.DONE and report.outcome is not None:
            try:
                self._take(report.outcome)
            except Exception as exc:
                report = RetrainReport(ReportKind.ERROR, f"cannot load the new model: {exc}")
        if report.kind is ReportKind.ERROR:
            self._retrain_text = f"retrain failed (the active model stays): {report.text}"
        final = report.kind is not ReportKind.STAGE
        title, colour = _finish_note(report.kind, refused=self.pending is not None)
        for tab in self.tabs():
            if final:  # the table and comparison first: the retrain's sentence refers to them
                tab.refresh_models()
                tab.show_label_mix(self.label_mix())
            tab.show_retrain()
            if final:
                tab.notify(title, self._retrain_text, colour)

    def _take(self, outcome: RetrainOutcome) -> None:
        """Load a finished retrain's model; rank with it only if the retrain activated it."""
        try:
            self.resources.add_model(qmodel_from_store(self.store, outcome.version), "store")
        except Exception:
            if outcome.activated:  # the store must not name a model this app cannot load
                self.store.set_active_model(
                    self.resources.current.version, reason="the new model could not be loaded"
                )
            raise
        self.last_outcome = outcome
        new = f"**{_short(outcome.version)}**"
        if outcome.activated:
            self.resources.use(outcome.version)
            self.pending = None
            fitted = outcome.n_executions - len(outcome.held_out)
            self._retrain_text = (
                f"Model {new} is now active: {outcome.why}. It was fitted on {fitted} "
                f"executions; {len(outcome.held_out)} were held out."
            )
        else:
            self.pending = outcome
            self._retrain_text = (
                f"Model {new} is stored but **not active**: {outcome.why}. "
                f"{self.resources.current.label} keeps ranking."
            )

    def _broadcast_retrain(self) -> None:
        for tab in self.tabs():
            tab.show_retrain()

    # ------------------------------------------------------------------ suggestions
    def start_suggest(self) -> bool:
        """Rank unlabelled starts by how much a label would teach the model, in the background
        (progress shown in every tab; cancel_suggest stops it)."""
        ranking = self.resources.current
        with self._suggest_lock:
            if self._suggesting or ranking.model is None:
                return False
            self._suggesting = True
            cancel = self._suggest_cancel = threading.Event()

        def work() -> None:
            from knotlab.core.selection.acquisition import rank_for_labelling, score_starts

            try:
                self._suggest_progress("loading the unlabelled starts", 0.0)
                states = self.store.start_states_to_label()
                t0 = time.perf_counter()
                last = [-SUGGEST_REPORT_S]

                def report(done: int, total: int) -> None:
                    now = time.perf_counter()
                    if now - last[0] >= SUGGEST_REPORT_S or done == total:
                        last[0] = now
                        self._suggest_progress(
                            f"scoring start {done} of {total} ({time.perf_counter() - t0:.0f} s)",
                            done / max(total, 1),
                        )

                assert ranking.model is not None
                scores = score_starts(
                    [(f"{st.state_id}", st.cloud_n3) for st in states],
                    ranking.featurizer,
                    ranking.model,
                    self.resources.start_scans,
                    stop=cancel.is_set,
                    report=report,
                )
                if cancel.is_set():
                    kept = "the previous order is kept" if self.suggested else "no order yet"
                    text = f"cancelled after {len(scores)} of {len(states)} starts; {kept}"
                else:
                    order = rank_for_labelling(scores, by="combined", seed=0)
                    self.suggested = [int(r.score.key) for r in order]
                    by_id = {st.state_id: st for st in states}
                    top = [
                        f"{r.rank}. `{by_id[int(r.score.key)].provenance.task_id}` "
                        f"(Q margin {r.score.margin:.3f}, NN/greedy disagree: "
                        f"{'yes' if r.score.disagreement else 'no'})"
                        for r in order[:5]
                    ]
                    text = (
                        f"{len(order)} starts ranked by {ranking.label} in "
                        f"{time.perf_counter() - t0:.0f} s; first:  \n" + "  \n".join(top)
                    )
            except Exception as exc:
                log.exception("suggest failed")
                text = f"suggest failed: {type(exc).__name__}: {exc}"
            with self._suggest_lock:
                self._suggesting = False
            self._suggest_progress(text, 1.0)

        threading.Thread(target=work, name="suggest", daemon=True).start()
        return True

    def cancel_suggest(self) -> bool:
        """Stop a running suggestion at its next start; False when none runs."""
        with self._suggest_lock:
            if not self._suggesting:
                return False
            self._suggest_cancel.set()
        self._suggest_progress("cancelling...", self._suggest_fraction)
        return True

    def _suggest_progress(self, text: str, fraction: float) -> None:
        self.suggest_text, self._suggest_fraction = text, fraction
        for tab in self.tabs():
            tab.show_suggest(text, self._suggesting, fraction)

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
    """Seed the store with the shipped model's training labels, load the models the app can
    rank with and pick the active one; returns a description.

    ``model_arg`` (a model file or a stored version) becomes the active model. Without it the
    store's active model ranks; a store that never had one starts with the shipped default
    model, else the newest stored one, else nearest neighbour. The pick is persisted in the
    store, so a restarted app ranks with the same model, never merely the newest.
    """
    from knotlab.core.errors import InvalidInputError
    from knotlab.core.selection.qmodel import QModel

    notes = []
    shipped: RankingModel | None = None
    if default_model.exists():
        try:
            shipped = app_resources.add_model(QModel.load(default_model), str(default_model))
        except Exception as exc:
            notes.append(f"{default_model} skipped: {exc}")
    if shipped is not None and shipped.model is not None:
        try:
            report = seed_shipped_labels(store, app_resources, shipped.model, default_model)
            if report.note or report.added_executions:
                print(report.describe(), flush=True)
        except Exception as exc:  # labels are an aid to retraining, not needed to label
            notes.append(f"the shipped model's training labels were not seeded: {exc}")
    stored_versions = [m.version for m in store.list_models()]
    for version in stored_versions:
        if app_resources.loaded(version) is not None:
            continue  # the shipped model, stored with its labels, keeps its file's name
        try:
            app_resources.add_model(qmodel_from_store(store, version), "store")
        except Exception as exc:  # a model of another library stays in the store, unused
            notes.append(f"stored model {version} skipped: {exc}")
    active = store.active_model()
    if model_arg is not None:
        path = Path(model_arg)
        if path.exists():
            chosen = app_resources.add_model(QModel.load(path), str(path))
        elif (found := app_resources.loaded(model_arg)) is not None:
            chosen = found
        else:
            raise InvalidInputError(
                f"--model {model_arg!r} is neither a model file nor a stored model version "
                f"(stored: {', '.join(stored_versions) or 'none'})"
            )
        _persist(store, app_resources, chosen, f"--model {model_arg}")
    elif active is not None and (active.version is None or app_resources.loaded(active.version)):
        app_resources.use(active.version)
    else:
        loaded = app_resources.models()
        newest_stored = [r for r in loaded if r.source == "store"]
        pick = shipped or (newest_stored[-1] if newest_stored else None)
        app_resources.use(None if pick is None else pick.version)
        if active is None:  # a new store: this pick is its first active model
            why = "the shipped default model" if pick is shipped else "the newest stored model"
            _persist(store, app_resources, pick, why if pick is not None else "no model fits")
        else:  # e.g. another --library this run: the store keeps its choice for later
            notes.append(
                f"the active model {_short(active.version)} does not fit this library; "
                f"ranking with {app_resources.current.label} for now"
            )
    for note in notes:
        log.warning(note)
    return app_resources.current.label


def _persist(
    store: Store, resources: AppResources, ranking: RankingModel | None, reason: str
) -> None:
    """Rank with ``ranking`` (None: nearest neighbour) and record it as the active model."""
    version = None if ranking is None else ranking.version
    if ranking is not None and ranking.model is not None:
        save_qmodel_to_store(store, ranking.model, resources.library_hash, [])
    store.set_active_model(version, reason=_clip(reason))
    resources.use(version)

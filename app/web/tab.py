"""One browser tab: wires its session (logic), scene drawer and panels (drawing) together.

Every GUI event lands here on one of viser's pool threads; the session serialises them. An
action the protocol does not allow right now becomes a notification, never a crash.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import threading
import time
from collections.abc import Callable
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Literal

import viser

from knotlab.app.episodes import store_episode
from knotlab.app.web.inspect import Inspector
from knotlab.app.web.inspect_panel import InspectPanel
from knotlab.app.web.panels import Actions, LabelPanels
from knotlab.app.web.playback_panel import PlaybackPanel
from knotlab.app.web.scene import MODEL_SPEED, BrowserScale, SceneDrawer, browser_scale_of
from knotlab.app.web.session import FRAME_DT, LabelSession
from knotlab.app.web.session_records import (
    STOP_MODEL_KEY,
    DriveOutcome,
    Phase,
    SessionError,
    SessionView,
)
from knotlab.app.web.sim_pool import SimPoolClosedError
from knotlab.core.errors import KnotlabError
from knotlab.core.world.frames import FrameRecorder
from knotlab.labeling_db.errors import ConflictError

if TYPE_CHECKING:
    from knotlab.app.web.server import LabelApp
    from knotlab.labeling_db.store import LabelMix

log = logging.getLogger(__name__)
NotifyColour = Literal["blue", "green", "yellow", "red"]
NAME_KEY = "knotlab.labeller"  # browser local storage key of the labeller's name


class LabelTab:
    """The controller of one connected client."""

    def __init__(self, app: LabelApp, client: viser.ClientHandle) -> None:
        self.app = app
        self.client = client
        self.session: LabelSession | None = None
        self.closed = False
        self._follow = False
        self._model_mode = False  # label where the model goes (the Label tab's checkbox)
        self._driver: threading.Thread | None = None  # runs the model's steps while it drives
        self._driver_lock = threading.Lock()
        # Model redraws come from the retrain thread and from switches: one at a time, each
        # reading the app's state inside it, so a stale table never lands after a fresh one.
        self._models_lock = threading.Lock()
        self._disagreements: dict = {}
        self.timings: dict[str, float] = {}  # last measured latencies (bench/app_latency.py)
        self.ready = threading.Event()  # a first state is drawn
        # Asked before the panels are built: the browser answers in the order it was asked, so
        # asked after them the answers waited for its ~140 panel messages to be handled.
        self._browser_facts = _BrowserFacts(client)
        self.drawer = SceneDrawer(client, on_pick=self.select, lite=app.lite_rendering)
        self.panels = LabelPanels(
            client,
            Actions(
                select=self.select,
                try_=self.try_selected,
                accept=lambda: self._act(lambda s: s.accept(), labels=True),
                reject=lambda: self._act(lambda s: s.reject()),
                dead_end=lambda: self._act(lambda s: s.dead_end(), labels=True),
                resample=lambda: self._act(lambda s: s.resample(), look=True, labels=True),
                undo=lambda: self._act(lambda s: s.undo(), look=True, labels=True),
                retrain=self.retrain,
                use_model=self.use_model,
                use_anyway=self.use_anyway,
                toggle_warped=lambda _on: self._redraw_warped(),
                suggest=self.suggest,
                cancel_suggest=self.cancel_suggest,
                agreement=self.agreement,
                open_disagreement=self.open_disagreement,
                follow=self.follow,
                model_mode=self.model_mode,
                stop_model=self.stop_model,
            ),
        )
        with self.panels.tabs.add_tab("Inspect", icon=viser.Icon.ZOOM_QUESTION):
            self.inspector = Inspector(app.resources, app.sim_pool)
            self.inspect = InspectPanel(
                client,
                self.inspector,
                current_nodes=lambda: None if self.session is None else self.session.nodes_k3,
                start_nodes=app.start_nodes,
                drawing=lambda enter=False: self.drawer.drawing("inspect", enter=enter),
                frame=self.drawer.frame_points,
                back=self.back_to_labelling,
            )
        with self.panels.tabs.add_tab("Playback", icon=viser.Icon.MOVIE):
            self.playback = PlaybackPanel(
                client,
                lambda episode_id: store_episode(app.store, episode_id, app.resources.library),
                lambda labelling: (
                    self.back_to_labelling() if labelling else self.drawer.show_only("playback")
                ),
                inspect=self.inspect.inspect_nodes,
                task=app.resources.task.name,
                frame=self.drawer.frame_points,
            )
        self.refresh_models()
        self.show_retrain()
        self.show_label_mix(app.label_mix())

    # ------------------------------------------------------------------ start
    def open(self) -> None:
        """Ask for the labeller's name (remembered by the browser) and start labelling."""
        self.drawer.browser, name = self._browser_facts.result()
        if name and name.strip():
            self.begin(name)
        else:
            self.panels.ask_name(self.begin)

    def begin(self, name: str) -> None:
        """Start (or resume) this labeller's session; when it is open in another tab, offer to
        take it over (one labeller labels in one tab at a time)."""
        other = self.app.labelling_tab(name.strip(), besides=self)
        if other is not None:
            self.panels.confirm(
                "Your episode is open in another tab",
                f"**{name.strip()}** is labelling in another tab or browser. Take the episode "
                "over here? That tab stops labelling; nothing accepted is lost.",
                "Take it over",
                lambda: self._take_over(other, name),
                on_no=lambda: self.panels.ask_name(self.begin),
            )
            return
        self._begin(name)

    def _take_over(self, other: LabelTab, name: str) -> None:
        other.taken_over()
        self._begin(name)

    def taken_over(self) -> None:
        """Another tab took this labeller's episode over: stop labelling here and say so."""
        session, self.session = self.session, None
        if session is None:
            return
        self.drawer.stop_animation()
        self.panels.show(session.detach())
        self._notify(
            "taken over", "your episode continues in another tab; reload here to label", "yellow"
        )

    def _begin(self, name: str) -> None:
        """Start (or resume) this labeller's session now."""
        try:
            pool = self.app.sim_pool
            session = LabelSession(
                self.app.store,
                self.app.resources,
                name,
                simulate=None if pool is None else pool.simulate,
            )
            view = session.start()
        except (SessionError, KnotlabError) as exc:  # a name or store the user can fix: ask again
            log.info("client %s: cannot start: %s", self.client.client_id, exc)
            self.panels.ask_name(self.begin, error=str(exc))
            return
        except Exception as exc:
            self._notify("cannot start labelling", str(exc), "red")
            log.exception("client %s: cannot start", self.client.client_id)
            return
        # Remembered only once it started: a refused name is not offered again on a reload.
        self.client.local_storage.set_item(NAME_KEY, name.strip())
        if self.closed:
            session.close()
            return
        self.session = session
        if self._follow:
            session.prefer = lambda: self.app.suggested
        if self._model_mode:
            session.set_model_mode(True)
        self._draw(look=True)
        self.ready.set()
        self._drive_if_needed()
        log.info("client %s: %s labels %s", self.client.client_id, name, view.task_id)

    def back_to_labelling(self) -> None:
        """Show the labelling state again (after Inspect or a playback drew theirs), framed."""
        if self.closed or self.drawer.showing == "label":
            return
        self.drawer.show_only("label")
        if self.session is not None:
            self.drawer.frame(self.session.view())

    # ------------------------------------------------------------------ actions
    def select(self, rank: int) -> None:
        """Select a candidate by rank (3D click, list button or hotkey)."""
        self._act(lambda s: s.select(rank), candidates_only=True)

    def try_selected(self) -> None:
        """Simulate the selected candidate while its animation plays."""
        session = self.session
        if session is None:
            return
        self.back_to_labelling()  # a labelling key pressed while Inspect showed its state
        view = session.view()
        if view.phase is not Phase.CHOOSING or view.selected is None:
            self._notify("nothing to try", "select a candidate first", "yellow")
            return
        recorder = FrameRecorder(FRAME_DT)
        t0 = time.perf_counter()
        self.drawer.show_warped(None, None)
        trying = _trying(view)
        with self.client.atomic():
            self.drawer.draw_candidates(trying)  # the tried path alone
            self.panels.show(trying)
        self.drawer.animate(recorder, session.candidate(view.selected), view.rope_nodes_k3)
        try:
            session.try_selected(recorder)
        except SessionError as exc:
            self.drawer.stop_animation()
            self._notify("cannot try", str(exc), "yellow")
            return
        except Exception as exc:
            self.drawer.stop_animation()
            if self._gone(exc):
                log.info("client %s: try dropped: %s", self.client.client_id, _why(exc))
                return
            self._notify("the simulation failed", f"{type(exc).__name__}: {exc}", "red")
            log.exception("try failed")
            self._draw()
            return
        if self.closed:  # the tab went away during the try: nobody to show it to
            return
        first = self.drawer.first_frame_at
        if first is not None:
            self.timings["try_to_first_frame_s"] = first - t0
        self.timings["try_s"] = time.perf_counter() - t0
        self.panels.show(session.view())

    def _act(
        self,
        action: Callable[[LabelSession], object],
        *,
        look: bool = False,
        candidates_only: bool = False,
        labels: bool = False,
    ) -> None:
        """Run a protocol action and redraw; ``labels``: it may store or remove labels (an
        abandoned rope's labels leave the training set), so every retrain panel is updated."""
        session = self.session
        if session is None:
            return
        self.back_to_labelling()  # a labelling key pressed while Inspect showed its state
        t0 = time.perf_counter()
        try:
            action(session)
        except SessionError as exc:
            self._notify("not now", str(exc), "yellow")
            return
        except ConflictError as exc:  # the episode changed elsewhere: a sentence, then resync
            log.info("client %s: %s", self.client.client_id, exc)
            self._notify(
                "this episode changed elsewhere",
                "it was labelled or ended in another tab; showing its current state",
                "yellow",
            )
            with contextlib.suppress(Exception):
                session.start()
            self._draw(look=True)
            return
        except Exception as exc:
            self._notify("error", f"{type(exc).__name__}: {exc}", "red")
            log.exception("action failed")
            return
        if labels:
            self.app.labels_changed()
        self.drawer.stop_animation()
        if candidates_only:
            view = session.view()
            with self.client.atomic():
                self.drawer.draw_candidates(view)
                self.panels.show(view)
            self._redraw_warped()
        else:
            self._draw(look=look)
        self.timings["action_to_drawn_s"] = time.perf_counter() - t0
        self._drive_if_needed()  # a new rope in model mode: the model drives it first

    # ------------------------------------------------------------------ the model drives
    def model_mode(self, on: bool) -> None:
        """The checkbox: label where the model goes (on), or along the expert's own episode."""
        self._model_mode = on
        session = self.session
        if session is None:
            return
        self.back_to_labelling()
        session.set_model_mode(on)
        self._draw()
        self._drive_if_needed()

    def stop_model(self) -> None:
        """S: stop the model after its current step; label the state it has reached."""
        session = self.session
        if session is None:
            return
        try:
            view = session.stop_model()
        except SessionError as exc:
            self._notify("not now", str(exc), "yellow")
            return
        self.panels.show(view)

    def _drive_if_needed(self) -> None:
        """Start the thread that runs the model's steps when the session is in the MODEL phase."""
        session = self.session
        if session is None or self.closed or session.view().phase is not Phase.MODEL:
            return
        with self._driver_lock:
            if self._driver is not None and self._driver.is_alive():
                return
            self._driver = threading.Thread(
                target=self._drive,
                args=(session,),
                name=f"model-drives-{self.client.client_id}",
                daemon=True,
            )
            self._driver.start()

    def _drive(self, session: LabelSession) -> None:
        """Show each state and the model's choice, execute it fast-forwarded, until it hands
        the rope over (or ties the knot: then the next start)."""
        while self._still_driving(session):
            view = session.view()
            if view.phase is not Phase.MODEL or not view.candidates:
                break
            # Not pulled back from Inspect or a playback: the model goes on driving behind it
            # (into the hidden labelling view), and the labeller comes back to where it is.
            labelling = self.drawer.showing == "label"
            chosen = view.candidates[0]
            view.message = (
                f"the model executes its choice #{chosen.ranked.rank} {chosen.ranked.demo_key} "
                f"({STOP_MODEL_KEY} stops it after this step)"
            )
            with self.client.atomic():
                if labelling:
                    self.drawer.draw(_trying(dataclasses.replace(view)), look=False)
                self.panels.show(view)
            recorder = FrameRecorder(FRAME_DT)
            anim = self.drawer.animate(recorder, chosen, view.rope_nodes_k3, speed=MODEL_SPEED)
            try:
                outcome = session.drive_step(recorder)
            except Exception as exc:
                self.drawer.stop_animation()
                if self._gone(exc):
                    log.info("client %s: drive dropped: %s", self.client.client_id, _why(exc))
                    break
                self._notify("the model's step failed", f"{type(exc).__name__}: {exc}", "red")
                log.exception("drive step failed")
                with contextlib.suppress(SessionError):
                    session.stop_model()  # the next step hands the rope over
                continue
            anim.join(timeout=30.0)  # the fast-forwarded execution plays to its end first
            if outcome is DriveOutcome.STOPPED:
                break
            after = session.view()
            if outcome is DriveOutcome.TIED:
                self._notify("the model tied the knot", after.message, "green")
                if self.drawer.showing == "label":
                    self._draw(look=True)
            elif outcome is DriveOutcome.HANDED_OVER:
                self._notify("your turn", after.message, "blue")
        if self._still_driving(session):
            self.drawer.stop_animation()
            if self.drawer.showing == "label":
                self._draw()
            else:
                self.panels.show(session.view())
        with self._driver_lock:
            self._driver = None
        # A rope that entered the MODEL phase while this loop was ending (a quick untick and
        # tick, an accept that claimed the next start) found the driver still alive: drive it.
        self._drive_if_needed()

    def _still_driving(self, session: LabelSession) -> bool:
        """The tab is open and still labels with ``session`` (not closed, not taken over)."""
        return not self.closed and self.session is session

    def _draw(self, look: bool = False) -> None:
        session = self.session
        if session is None or self.closed:
            return
        view = session.view()
        with self.client.atomic():  # one batch: the browser redraws once, not per message
            self.drawer.draw(view, look=look)
            self.panels.show(view)
            self._redraw_warped()
            self._show_progress()
        self.client.flush()

    def _redraw_warped(self) -> None:
        session = self.session
        if session is None:
            return
        view = session.view()
        on = bool(self.panels.show_warped.value)
        if on and view.selected is not None and view.phase is Phase.CHOOSING:
            self.drawer.show_warped(view.selected, session.warped_demo_cloud(view.selected))
        else:
            self.drawer.show_warped(None, None)

    def _show_progress(self) -> None:
        session = self.session
        if session is None:
            return
        progress = self.app.store.progress(session.labeller)
        today = datetime.now(UTC).date()
        n_today = sum(
            1
            for lab in self.app.store.labels(labeller=session.labeller)
            if lab.labelled_at.astimezone(UTC).date() == today
        )
        view = session.view()
        self.panels.show_progress(n_today, progress.labels, progress.start_states_remaining, view)

    # ------------------------------------------------------------------ models
    def retrain(self) -> None:
        """Start a retrain (refused with a message while one runs)."""
        if not self.app.start_retrain():
            self._notify("a retrain is already running", "wait for it to finish", "yellow")

    def suggest(self) -> None:
        """Rank the unlabelled starts for labelling (refused while running or without a model)."""
        if not self.app.start_suggest():
            self._notify("cannot suggest now", "one is running, or there is no model", "yellow")

    def agreement(self) -> None:
        """Per labeller pair: top-1 agreement, Cohen's kappa, dead ends; list disagreements."""
        from knotlab.core.selection.agreement import pairwise_agreement

        pairs = pairwise_agreement(self.app.store.state_visits())
        p = self.panels
        if not pairs:
            p.agreement_table.content = "fewer than two labellers share a state yet"
            return
        rows = ["| pair | shared | top-1 | kappa | dead ends both / one |", "|---|---|---|---|---|"]
        self._disagreements = {}
        for pa in pairs:
            top1 = f"{pa.n_agree / pa.n_compared:.2f}" if pa.n_compared else "-"
            kappa = "n/a" if pa.kappa is None else f"{pa.kappa:.2f}"
            one = pa.dead_end_only_a + pa.dead_end_only_b
            rows.append(
                f"| {pa.labeller_a} / {pa.labeller_b} | {pa.n_shared} | {top1} | {kappa} | "
                f"{pa.dead_end_both} / {one} |"
            )
            for d in pa.disagreements:
                label = (
                    f"{d.start} step {d.step_index + 1}: {pa.labeller_a} {d.demo_a}, "
                    f"{pa.labeller_b} {d.demo_b}"
                )
                self._disagreements[label] = d
        p.disagreements.options = tuple(self._disagreements) or ("-",)
        p.open_disagreement.disabled = not self._disagreements
        p.agreement_table.content = "\n".join(rows)  # last: the table says the panel is ready

    def open_disagreement(self, label: str) -> None:
        """Rebuild a disagreed state (start + earlier choices) and show both picks in Inspect."""
        d = self._disagreements.get(label)
        if d is None:
            return
        try:
            nodes = self.app.start_nodes_of(d.start)
            view = self.inspector.load_path(nodes, d.path, f"{label}")
        except Exception as exc:
            self._notify("cannot open", str(exc), "red")
            return
        self.inspect.open_pair(view, d.demo_a, d.demo_b)
        self._notify("opened in Inspect", f"{label}: the Inspect tab shows it", "blue")

    def follow(self, on: bool) -> None:
        """Claim the next ropes in the suggested order (or the oldest first)."""
        self._follow = on
        if self.session is not None:
            self.session.prefer = (lambda: self.app.suggested) if on else None

    def cancel_suggest(self) -> None:
        """Stop a running suggestion at its next start (the last finished order stays)."""
        if not self.app.cancel_suggest():
            self._notify("nothing to cancel", "no suggestion is running", "yellow")

    def show_suggest(self, text: str, running: bool, fraction: float = 0.0) -> None:
        """Redraw the suggestion status and progress."""
        if not self.closed:
            self.panels.show_suggest(text, running, fraction)

    def use_model(self, version: str | None) -> None:
        """Rank every tab's next states with model ``version``, once the labeller confirms."""
        current = self.app.resources.current
        if version == current.version:
            self.notify("already active", f"next states are ranked by {current.label}")
            return
        row = next((r for r in self.app.model_rows() if r.version == version), None)
        label = "nearest neighbour" if row is None or version is None else row.label
        score = None if row is None else row.top1
        held = "" if score is None else f"  \nIts validation top-1: {score:.3f}."
        self.panels.confirm(
            "Switch the model?",
            f"Every tab's next state will be ranked by **{label}** instead of "
            f"**{current.label}**.{held}",
            "Yes, rank with it",
            lambda: self._switch(version, f"switched to it by {self._who()}"),
        )

    def use_anyway(self) -> None:
        """Activate the new model a retrain kept inactive, once the labeller confirms."""
        pending = self.app.pending
        if pending is None:
            self.notify("nothing to use", "no new model is waiting", "yellow")
            return
        worse = ""
        if pending.verdict is not None:
            new, old = pending.verdict.candidate, pending.verdict.active
            worse = (
                f"  \nOn the same {new.n_states} held-out states its top-1 is "
                f"{new.top1:.3f}, the active model's {old.top1:.3f}."
            )
        self.panels.confirm(
            "Use the new model anyway?",
            f"Model **{pending.version[:8]}** is not active: {pending.why}."
            f"{worse}  \nEvery tab's next state will be ranked by it.",
            "Yes, rank with it",
            lambda: self._switch(pending.version, f"used anyway by {self._who()}"),
        )

    def _switch(self, version: str | None, reason: str) -> None:
        try:
            chosen = self.app.use_model(version, reason=reason)
        except Exception as exc:
            self._notify("cannot switch", f"{type(exc).__name__}: {exc}", "red")
            log.exception("switching models failed")
            return
        self.notify("model switched", f"next states are ranked by {chosen.label}", "green")

    def _who(self) -> str:
        """Who is acting in this tab (for the store's record of model switches)."""
        return self.session.labeller if self.session is not None else "a labeller"

    def refresh_models(self) -> None:
        """Redraw the active model, the model list, and the last retrain's comparison."""
        # The line saying which model ranks goes last: whoever sees it changed (a labeller, a
        # test) then finds the table and the comparison already agreeing with it.
        with self._models_lock:
            text, rows = self.app.active_text(), self.app.model_rows()
            self.panels.show_models(rows)
            self.panels.show_comparison(self.app.last_outcome, self.app.pending is not None)
            self.panels.show_active(text)

    def show_label_mix(self, mix: LabelMix) -> None:
        """Redraw the labels a retrain would fit on (not in a tab that has gone)."""
        if not self.closed:
            self.panels.show_label_mix(mix)

    def show_retrain(self) -> None:
        """Redraw the retrain progress."""
        self.panels.show_retrain(*self.app.retrain_state())

    def _notify(self, title: str, body: str, color: NotifyColour) -> None:
        if self.closed:  # nobody to show it to (viser would queue it on a closed connection)
            return
        try:
            self.client.add_notification(title, body, auto_close_seconds=6.0, color=color)
        except Exception:  # the tab may be gone
            log.debug("notification to a closed client dropped", exc_info=True)

    def notify(self, title: str, body: str, color: NotifyColour = "blue") -> None:
        """Show a notification in this tab."""
        self._notify(title, body, color)

    def _gone(self, exc: Exception) -> bool:
        """Whether ``exc`` only says that this tab or the app went away meanwhile (a try cut
        short by it has nobody to report to)."""
        return self.closed or isinstance(exc, SimPoolClosedError)

    def close(self) -> None:
        """The browser tab went away: no half label, release an untouched start."""
        self.closed = True
        self.drawer.stop_animation()
        if self.session is not None:
            self.session.close()
        self.inspector.close()
        self.playback.stop()


def _why(exc: Exception) -> str:
    """One line naming an exception."""
    return f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__


def _trying(view: SessionView) -> SessionView:
    """``view`` as shown while its selected candidate is simulated."""
    view.phase = Phase.TRYING
    view.message = "simulating..."
    return view


class _BrowserFacts:
    """The browser's scale and remembered labeller name, asked on a thread of its own."""

    def __init__(self, client: viser.ClientHandle) -> None:
        self._client = client
        self._scale = BrowserScale()
        self._name: str | None = None
        self._thread = threading.Thread(target=self._ask, name="browser-facts", daemon=True)
        self._thread.start()

    def _ask(self) -> None:
        self._scale = browser_scale_of(self._client)
        try:
            self._name = self._client.local_storage.get_item(NAME_KEY, timeout=3.0)
        except (RuntimeError, TimeoutError) as exc:
            log.info(
                "client %s: no local storage (%s); asking the name", self._client.client_id, exc
            )

    def result(self) -> tuple[BrowserScale, str | None]:
        """(scale, name or None), waiting for the browser's answers (at most ~6 s)."""
        self._thread.join()
        return self._scale, self._name

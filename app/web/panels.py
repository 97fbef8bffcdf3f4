"""One tab's GUI: name prompt, status, ranked candidate list, actions with hotkeys, progress,
retrain (the labels it would fit on, how a new model compared) and model list, and a
confirmation dialog. Widgets only: every action calls back into the tab controller.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import viser

from knotlab.app.web.scene import candidate_label, rank_colour
from knotlab.app.web.session_records import STOP_MODEL_KEY, Phase, SessionView

if TYPE_CHECKING:
    from knotlab.app.web.jobs import HeldOutScores, RetrainOutcome
    from knotlab.app.web.server import ModelRow
    from knotlab.labeling_db.store import LabelMix

MAX_LISTED = 9  # hotkeys 1-9 select by rank
# The actions' hotkeys (the ranks' 1-9 besides); none is a key viser's camera moves on.
HOTKEYS: tuple[tuple[str, str], ...] = (
    ("Try the selected candidate", "enter"),
    ("Accept", "Y"),
    ("Reject", "N"),
    ("Dead end", "F"),
    ("New rope", "R"),
    ("Undo last label", "U"),
    ("Stop the model here", STOP_MODEL_KEY),
    ("Label where the model goes (on / off)", "M"),
)
_UNSET = object()
# A banner for a lost server. viser keeps the panel on screen when its websocket closes, only
# dimmed and frozen (an inline style with "pointer-events: none" on the GUI's wrapper); this
# element is inside that wrapper, so a CSS rule on that style shows it then, with no script.
OFFLINE_TEXT = (
    "The knotlab server is not reachable: nothing you do here is stored now. "
    "This page reconnects by itself when the server is back."
)
OFFLINE_BANNER = f"""<style>
.knotlab-offline {{ display: none; }}
/* Notes at the canvas's bottom-left, not its top-left: a state's candidate paths and their
   captions rise above the rope, into the top of the view (viser places them top-left). */
.mantine-Notifications-root {{ top: auto !important; bottom: 3.5em !important; }}
div[style*="pointer-events: none"] .knotlab-offline {{
  display: block; position: fixed; top: 0; left: 0; right: 0; z-index: 1000;
  padding: 0.8em 1em; background: #a61e1e; color: white; font-weight: bold;
  text-align: center; font-size: 1.05em;
}}
</style>
<div class="knotlab-offline" role="alert">{OFFLINE_TEXT}</div>"""


@dataclass(frozen=True)
class Actions:
    """What the panels' buttons and hotkeys call."""

    select: Callable[[int], None]
    try_: Callable[[], None]
    accept: Callable[[], None]
    reject: Callable[[], None]
    dead_end: Callable[[], None]
    resample: Callable[[], None]
    undo: Callable[[], None]
    retrain: Callable[[], None]
    use_model: Callable[[str | None], None]  # a model version; None: nearest neighbour
    use_anyway: Callable[[], None]  # activate a new model the retrain kept inactive
    toggle_warped: Callable[[bool], None]
    suggest: Callable[[], None]
    cancel_suggest: Callable[[], None]
    agreement: Callable[[], None]
    open_disagreement: Callable[[str], None]
    follow: Callable[[bool], None]
    model_mode: Callable[[bool], None]  # label where the model goes: on / off
    stop_model: Callable[[], None]


def judged_suffix(rank: int, view: SessionView) -> str:
    """How a judged candidate reads in the list: a dead end is not a reject."""
    if rank in view.dead_ends:
        return " · dead end"
    if rank == view.model_failed:
        return " · model's: failed"
    return " · rejected" if rank in view.rejected else ""


def _bind(fn: Callable[[int], None], arg: int) -> Callable[[], None]:
    """fn with its argument fixed (a closure per rank: a lambda in a loop would share r)."""
    return lambda: fn(arg)


def _score(value: float | None) -> str:
    """A metric as the tables show it."""
    return "-" if value is None else f"{value:.3f}"


def label_mix_text(mix: LabelMix) -> str:
    """The labels a retrain would fit on: how many, and the oracle / human mix per labeller."""
    if not mix.shares:
        return "**Labels a retrain fits on:** none yet"
    head = f"**Labels a retrain fits on:** {mix.labels} states of {mix.executions} executions"
    if mix.dead_end_only:
        head += f", and {mix.dead_end_only} executions of dead ends only"
    lines = [head]
    for source in ("oracle", "human"):
        shares = mix.of_source(source)
        who = ", ".join(f"{sh.labeller} {sh.labels}" for sh in shares) or "none yet"
        lines.append(f"· {source}: {sum(sh.labels for sh in shares)} ({who})")
    return "  \n".join(lines)


def comparison_table(outcome: RetrainOutcome) -> str:
    """The new model and the active one side by side on the same held-out executions."""
    verdict = outcome.verdict
    if verdict is None:
        return ""
    new, old = verdict.candidate, verdict.active

    def cell(metric: str, title: str, scores: HeldOutScores) -> str:
        """A score; the new model's marked where the gate found it worse."""
        worse = scores is new and title in verdict.worse_on
        return _score(getattr(scores, metric)) + (" ▼" if worse else "")

    name_old = "nearest neighbour" if old.version is None else old.version[:8]
    # The old model is still active when the new one was kept out.
    role = "before" if outcome.activated else "active"
    rows = [
        f"| held out: {verdict.n_executions} executions | new {outcome.version[:8]} "
        f"| {role}: {name_old} |",
        "|---|---|---|",
        f"| states | {new.n_states} | {old.n_states} |",
    ]
    for metric, title in (("top1", "top-1"), ("top3", "top-3"), ("value_auc", "V-AUC")):
        rows.append(f"| {title} | {cell(metric, title, new)} | {cell(metric, title, old)} |")
    return "\n".join(rows)


def _call_with(fn: Callable[..., None], *args: object) -> Callable[[object], None]:
    """An event callback that ignores the event and calls ``fn(*args)``."""

    def callback(_event: object) -> None:
        fn(*args)

    return callback


class LabelPanels:
    """The GUI of one tab."""

    def __init__(self, client: viser.ClientHandle, actions: Actions) -> None:
        self.client = client
        self.actions = actions
        gui = client.gui
        icon = viser.Icon
        gui.set_panel_label("knotlab: label demonstrations")
        # Shown only while the server is unreachable (see OFFLINE_BANNER).
        self.offline_banner = gui.add_html(OFFLINE_BANNER)
        tabs = self.tabs = gui.add_tab_group()
        with tabs.add_tab("Label", icon=icon.HAND_CLICK):
            self.status = gui.add_markdown("loading your labelling state...")
            with gui.add_folder("Candidates (ranked)"):
                self.cand_buttons = [
                    gui.add_button(f"#{r}", visible=False, hint=f"select rank {r} (key {r})")
                    for r in range(1, MAX_LISTED + 1)
                ]
                self.show_warped = gui.add_checkbox("Show warped demo cloud", False)
                self.follow_suggested = gui.add_checkbox(
                    "Next rope: the suggested one", False, hint="Model tab: Suggest"
                )
                self.model_mode = gui.add_checkbox(
                    "Label where the model goes",
                    False,
                    hint="the model's own choices move each new rope until one fails; "
                    "you label that state",
                )
            # Disabled until the first state is shown: behind the name prompt they do nothing.
            with gui.add_folder("Actions"):
                self.try_button = gui.add_button(
                    "Try (Enter)", color="blue", icon=icon.PLAYER_PLAY, disabled=True
                )
                self.accept_button = gui.add_button(
                    "Accept (Y)", color="green", icon=icon.CHECK, disabled=True
                )
                self.reject_button = gui.add_button(
                    "Reject (N)", color="red", icon=icon.X, disabled=True
                )
                self.dead_button = gui.add_button(
                    "Dead end (F)", color="orange", icon=icon.SKULL, disabled=True
                )
                self.resample_button = gui.add_button(
                    "New rope (R)", icon=icon.REFRESH, disabled=True
                )
                self.undo_button = gui.add_button(
                    "Undo last label (U)", icon=icon.ARROW_BACK_UP, disabled=True
                )
                self.stop_model_button = gui.add_button(
                    f"Stop the model here ({STOP_MODEL_KEY})",
                    color="orange",
                    icon=icon.PLAYER_STOP,
                    visible=False,
                    hint="label the state the model has reached",
                )
            with gui.add_folder("Progress"):
                self.progress = gui.add_markdown("")
        with tabs.add_tab("Model", icon=icon.BRAIN):
            self.model_status = gui.add_markdown("")
            self.label_mix = gui.add_markdown("")
            self.retrain_button = gui.add_button("Retrain on all labels", icon=icon.PLAYER_PLAY)
            self.retrain_bar = gui.add_progress_bar(0.0, visible=False, animated=True)
            self.retrain_status = gui.add_markdown("")
            self.comparison = gui.add_markdown("")
            self.use_anyway_button = gui.add_button(
                "Use it anyway",
                color="orange",
                visible=False,
                hint="rank with the new model although it scored worse on held-out labels",
            )
            self.model_dropdown = gui.add_dropdown("Model", ("nearest neighbour",))
            # A button, not the dropdown's own update: a dropdown echoes its value back when
            # its options change (after a retrain), which must not switch models by itself.
            self.use_model_button = gui.add_button("Rank with this model")
            self.model_table = gui.add_markdown("")
            gui.add_markdown("**What to label next**")
            self.suggest_button = gui.add_button("Suggest what to label next")
            self.suggest_bar = gui.add_progress_bar(0.0, visible=False, animated=True)
            self.cancel_suggest_button = gui.add_button(
                "Cancel suggesting", color="red", icon=icon.X, visible=False
            )
            self.suggest_status = gui.add_markdown("")
            gui.add_markdown("**How far experts agree**")
            self.agreement_button = gui.add_button("Compute agreement")
            self.agreement_table = gui.add_markdown("")
            self.disagreements = gui.add_dropdown("Disagreement", ("-",))
            self.open_disagreement = gui.add_button("Open it in Inspect", disabled=True)
        self._model_options: dict[str, str | None] = {}
        self._sent: dict[tuple[int, str], object] = {}
        self._wire()

    def _wire(self) -> None:
        a = self.actions
        for r, button in enumerate(self.cand_buttons, start=1):
            button.on_click(_call_with(a.select, r))
        self.try_button.on_click(lambda _e: a.try_())
        self.accept_button.on_click(lambda _e: a.accept())
        self.reject_button.on_click(lambda _e: a.reject())
        self.dead_button.on_click(lambda _e: a.dead_end())
        self.resample_button.on_click(lambda _e: a.resample())
        self.undo_button.on_click(lambda _e: a.undo())
        self.stop_model_button.on_click(lambda _e: a.stop_model())
        self.model_mode.on_update(lambda _e: a.model_mode(bool(self.model_mode.value)))
        self.retrain_button.on_click(lambda _e: a.retrain())
        self.use_anyway_button.on_click(lambda _e: a.use_anyway())
        self.suggest_button.on_click(lambda _e: a.suggest())
        self.cancel_suggest_button.on_click(lambda _e: a.cancel_suggest())
        self.agreement_button.on_click(lambda _e: a.agreement())
        self.open_disagreement.on_click(lambda _e: a.open_disagreement(self.disagreements.value))
        self.follow_suggested.on_update(lambda _e: a.follow(bool(self.follow_suggested.value)))
        self.show_warped.on_update(lambda _e: a.toggle_warped(bool(self.show_warped.value)))

        @self.use_model_button.on_click
        def _(_e) -> None:
            if self.model_dropdown.value in self._model_options:
                a.use_model(self._model_options[self.model_dropdown.value])

        self._try = a.try_
        # While the name prompt is open, Enter submits it: the Enter hotkey is global, so
        # without this a keyboard-only labeller's Enter in the name field would be a Try.
        self._submit_name: Callable[[], bool] | None = None
        self._name_hint: Any = None  # the name dialog's message line, while it is open
        gui = self.client.gui
        action = {
            "Try the selected candidate": self._enter,
            "Accept": a.accept,
            "Reject": a.reject,
            "Dead end": a.dead_end,
            "New rope": a.resample,
            "Undo last label": a.undo,
            "Stop the model here": a.stop_model,
            "Label where the model goes (on / off)": self._toggle_model_mode,
        }
        keys: list[tuple[str, str, Callable[[], None]]] = [
            (label, key, action[label]) for label, key in HOTKEYS
        ]
        for r in range(1, MAX_LISTED + 1):
            keys.append((f"Select rank {r}", str(r), _bind(a.select, r)))
        self.commands = []
        for label, key, fn in keys:
            cmd = gui.add_command(label, hotkey=key)  # type: ignore[arg-type]
            cmd.on_trigger(_call_with(fn))
            self.commands.append(cmd)

    def _toggle_model_mode(self) -> None:
        """M: tick or untick "Label where the model goes" (its update callback acts on it)."""
        setattr(self.model_mode, "value", not self.model_mode.value)  # noqa: B010 (typed read-only)

    # ------------------------------------------------------------------ name
    def ask_name(self, on_name: Callable[[str], None], error: str | None = None) -> None:
        """A modal asking the labeller's name once per browser; Enter in the field, Enter on
        the button and a click all start (the field sits in a form, which submits on Enter).
        ``error``: why the last name could not start (shown in the dialog)."""
        self._set(self.status, "content", "*waiting for your name (in the dialog)*")
        modal = self.client.gui.add_modal("Who is labelling?")
        with modal:
            self.client.gui.add_markdown(
                "Your name is stored with every label you make (and kept in this browser)."
            )
            with self.client.gui.add_form(None) as form:
                name = self.client.gui.add_text("Your name", "")
            hint = self.client.gui.add_markdown(f"**cannot start**: {error}" if error else "")
            start = self.client.gui.add_button("Start labelling", color="green")
        lock = threading.Lock()
        self._name_hint = hint

        def submit() -> bool:
            """Start with the typed name, once; False when the field is still empty."""
            with lock:
                value = name.value.strip()
                if not value or self._submit_name is None:
                    return False
                self._submit_name = None
            modal.close()
            on_name(value)
            return True

        self._submit_name = submit

        @start.on_click
        def _(_e: object) -> None:
            self._submit_typed_name()

        @form.on_submit
        def _(_e: object) -> None:
            # viser's client sends field edits at most every 50 ms through one pending slot, which
            # the submit takes over: a key typed within 50 ms before Enter never reaches us
            # (docs/reference/viser.md). At a person's typing pace that does not happen.
            self._enter()

    def _enter(self) -> None:
        """Enter: submit the name prompt while it is open, else try the selected candidate."""
        if self._submit_name is None:
            self._try()
            return
        self._submit_typed_name()

    def _submit_typed_name(self) -> None:
        """Submit the open name prompt, waiting up to a second for the field's last edit."""
        submit = self._submit_name
        if submit is None:
            return
        # The field's last keystrokes may reach the server just after the Enter key or the
        # click does: viser sends field edits at most every 50 ms.
        deadline = time.monotonic() + 1.0
        while not submit() and self._submit_name is submit and time.monotonic() < deadline:
            time.sleep(0.05)
        # The same prompt still open: its field is empty. (A refused name opens a new prompt
        # with its own reason, which this must not overwrite.)
        if self._submit_name is submit:
            self._ask_for_a_name()

    def _ask_for_a_name(self) -> None:
        """An empty name was submitted: say so in the dialog."""
        if self._name_hint is not None:
            self._set(self._name_hint, "content", "**type your name first** (any name but empty)")

    # ------------------------------------------------------------------ state
    def show(self, view: SessionView) -> None:
        """Refresh status, candidate list and which actions are enabled."""
        phase = view.phase
        where = f"task `{view.task_id}`" if view.task_id else "no rope"
        step = f"step **{view.rollout_step + 1}** of {view.step_limit}"
        lines = [
            f"**{view.labeller}** · {where} · {step}",
            *([f"goal: {view.goal}"] if view.goal else []),
            f"ranked by: {view.model}",
            f"*{phase.value}*" + (f": {view.message}" if view.message else ""),
        ]
        if view.last_try is not None:
            t = view.last_try
            lines.append(f"tried #{t.rank} {t.demo_key}: **{t.summary}** ({t.wall_s:.1f} s)")
        self._set(self.status, "content", "  \n".join(lines))
        shown = {c.ranked.rank: c for c in view.candidates}
        for r, button in enumerate(self.cand_buttons, start=1):
            c = shown.get(r)
            self._set(button, "visible", c is not None)
            if c is None:
                continue
            rejected = r in view.rejected
            # A judged candidate's verdict takes the cost's place: the panel's width fits one
            # of the two, and a greyed-out candidate is not chosen by its cost any more.
            label = candidate_label(c) + (
                judged_suffix(r, view) or f" · cost {c.ranked.nn_cost:.3f}"
            )
            self._set(button, "label", label)
            self._set(button, "color", "gray" if rejected else rank_colour(r))
            self._set(button, "icon", viser.Icon.ARROW_RIGHT if r == view.selected else None)
            self._set(button, "disabled", phase is not Phase.CHOOSING or rejected)
        choosing, judging = phase is Phase.CHOOSING, phase is Phase.JUDGING
        acceptable = judging and view.last_try is not None and view.last_try.acceptable
        self._set(self.try_button, "disabled", not (choosing and view.selected is not None))
        self._set(self.accept_button, "disabled", not acceptable)
        self._set(self.reject_button, "disabled", not judging)
        self._set(self.dead_button, "disabled", not judging)
        # A closed session (its episode taken over in another tab) acts on nothing here.
        closed = phase is Phase.CLOSED
        self._set(
            self.resample_button,
            "disabled",
            closed or phase in (Phase.TRYING, Phase.MODEL, Phase.NO_STARTS),
        )
        busy = phase in (Phase.TRYING, Phase.MODEL)
        self._set(self.undo_button, "disabled", closed or busy)
        self._set(self.stop_model_button, "visible", phase is Phase.MODEL)
        for command in self.commands:  # the hotkeys too
            self._set(command, "disabled", closed)

    def _set(self, handle: object, prop: str, value: object) -> None:
        """Assign a GUI property only when it changes: every assignment is a websocket message,
        and a new state would otherwise resend ~50 of them."""
        key = (id(handle), prop)
        if self._sent.get(key, _UNSET) != value:
            setattr(handle, prop, value)
            self._sent[key] = value

    def show_progress(self, today: int, total: int, starts_left: int, view: SessionView) -> None:
        """Labels today and in total, starts left, step within the episode."""
        self.progress.content = (
            f"labels today: **{today}** · in total: **{total}**  \n"
            f"training starts left: **{starts_left}**  \n"
            f"this episode: step {view.rollout_step + 1} of {view.step_limit}"
            + ("".join(f"  \n· {h}" for h in view.history[-5:]))
        )

    # ------------------------------------------------------------------ models
    def show_models(self, rows: list[ModelRow]) -> None:
        """The model table (the active model marked) and the dropdown to switch."""
        self._model_options = {row.label: row.version for row in rows}
        self.model_dropdown.options = tuple(self._model_options)
        for row in rows:
            if row.active:
                self.model_dropdown.value = row.label  # type: ignore[misc]
        table = [
            "| | model | made | labels | top-1 | V-AUC |",
            "|---|---|---|---|---|---|",
        ]
        for row in rows:
            if row.version is None and not row.active:
                continue  # nearest neighbour is listed only while it ranks
            name = "nearest neighbour" if row.version is None else row.version[:8]
            mark = "**▶ active**" if row.active else ""
            table.append(
                f"| {mark} | {name} | {row.made} | {row.labels} | {_score(row.top1)} | "
                f"{_score(row.value_auc)} |"
            )
        self.model_table.content = "\n".join(table)

    def show_active(self, text: str) -> None:
        """Which model ranks every tab's next state."""
        self.model_status.content = text

    def show_label_mix(self, mix: LabelMix) -> None:
        """The labels a retrain would fit on, before it starts."""
        self.label_mix.content = label_mix_text(mix)

    def show_comparison(self, outcome: RetrainOutcome | None, pending: bool) -> None:
        """The last retrain's comparison, and "Use it anyway" while its model is kept out."""
        self.comparison.content = "" if outcome is None else comparison_table(outcome)
        self.use_anyway_button.visible = pending

    def confirm(
        self,
        title: str,
        body: str,
        yes: str,
        on_yes: Callable[[], None],
        on_no: Callable[[], None] | None = None,
    ) -> None:
        """Ask before doing something every tab feels; ``on_yes`` runs only on ``yes``,
        ``on_no`` (if given) on Cancel."""
        gui = self.client.gui
        modal = gui.add_modal(title)
        with modal:
            gui.add_markdown(body)
            yes_button = gui.add_button(yes, color="green")
            no_button = gui.add_button("Cancel")
        once = threading.Lock()

        @yes_button.on_click
        def _(_e: object) -> None:
            if once.acquire(blocking=False):  # a double click switches once
                modal.close()
                on_yes()

        @no_button.on_click
        def _(_e: object) -> None:
            if once.acquire(blocking=False):
                modal.close()
                if on_no is not None:
                    on_no()

    def show_suggest(self, text: str, running: bool, fraction: float) -> None:
        """Suggestion progress: bar, cancel button, status text, button state."""
        self.suggest_bar.visible = running
        self.suggest_bar.value = max(0.0, min(100.0, 100.0 * fraction))  # type: ignore[misc]
        self.cancel_suggest_button.visible = running
        self.suggest_status.content = text
        self.suggest_button.disabled = running

    def show_retrain(self, running: bool, text: str, fraction: float) -> None:
        """Retrain progress: bar, stage text, button state."""
        self.retrain_bar.visible = running
        percent = max(0.0, min(100.0, 100.0 * fraction))
        self.retrain_bar.value = percent  # type: ignore[misc]
        self.retrain_status.content = text
        self.retrain_button.disabled = running

"""One expert's labelling session (one browser tab): plain Python, no viser calls.

The protocol is the original system's (docs/reference/original_system.md, "Labelling protocol") in a
browser: the tab holds a claimed training start; its state is ranked (the greedy policy's own
ranking function); the expert selects a candidate and *tries* it in simulation, then accepts it (Y:
the label is stored in one transaction with the ranking shown, the model version and the rope after
the step), rejects it (N: state restored, candidate greyed out), marks the result a dead end (F:
stored, state restored) or abandons the rope (R). U undoes the last accepted label. A knot or the
step limit ends the episode and the next start is claimed.

Label where the model goes (``model_mode``): on each new start the ranking model's own first
choice is executed step after step (phase MODEL: the rope advances as the greedy policy would
move it) until that choice fails (a failed execution, no stage gained, a step back, or the step
limit without a knot) or the labeller stops it; the episode then begins at that state (the
store records which policy and model reached it, from which start, and the demos chosen on the
way) and the expert labels it as usual, the model's failed choice greyed out. A start the model
ties a knot from has nothing to label and is passed over.

Thread safety: viser runs callbacks on a thread pool, so every public method takes the session's
lock; ``try_selected`` holds it only to start and to finish, and refuses a second try meanwhile.
Shape suffixes: n = cloud points, k = rope nodes, g = grippers, t = waypoints.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Sequence
from typing import TypeAlias

import numpy as np

from knotlab.app.web.resources import AppResources, RankingModel
from knotlab.app.web.session_records import (
    STOP_MODEL_KEY,
    Candidate,
    DriveOutcome,
    Phase,
    SessionError,
    SessionView,
    TryResult,
)
from knotlab.core.execution.apply import ActionOutcome
from knotlab.core.experiments.labeller import start_rope_hash
from knotlab.core.failures import FailureKind
from knotlab.core.machine import NUMERIC_KIND_KEY, numeric_kind
from knotlab.core.outcomes import StepOutcome
from knotlab.core.registration import ScanResult
from knotlab.core.selection.labels import DeadEndState, LabelledStep
from knotlab.core.selection.ranking import RankedDemo, rank_demos
from knotlab.core.selection.summary_ranking import SummaryScan, summary_scan
from knotlab.core.world.frames import FrameRecorder
from knotlab.core.world.sim import RopeWorld, SimSnapshot
from knotlab.labeling_db.records import EpisodeInfo, StateProvenance
from knotlab.labeling_db.store import Store

FRAME_DT = 1.0 / 30.0  # s of simulated time between animation frames
# Names a person cannot label under: the simulated expert's (its labels are told apart by it).
RESERVED_NAMES: frozenset[str] = frozenset({"oracle"})
# A shown state's scan: in full, or from a stored summary with its candidates registered.
ShownScan: TypeAlias = ScanResult | SummaryScan
# How a try is simulated: (state, cloud, demo index, frame recorder) -> outcome.
Simulate = Callable[[SimSnapshot, np.ndarray, int, FrameRecorder], ActionOutcome]

DRIVING_NOW = f"the model is driving this rope: stop it first ({STOP_MODEL_KEY})"


class LabelSession:
    """One labeller's tab: claims a start, ranks states, runs tries, stores judgements."""

    def __init__(
        self,
        store: Store,
        resources: AppResources,
        labeller: str,
        *,
        world: RopeWorld | None = None,
        max_steps: int | None = None,
        simulate: Simulate | None = None,
    ) -> None:
        if not labeller.strip():
            raise SessionError("the labeller's name must not be empty")
        if labeller.strip().casefold() in RESERVED_NAMES:
            raise SessionError(
                f"{labeller.strip()!r} names the simulated expert; choose your own name"
            )
        self.store = store
        self.res = resources
        self.labeller = labeller.strip()
        self.step_limit = resources.task.step_limit if max_steps is None else max_steps
        self.max_steps = self.step_limit  # of this episode: the limit less its first step
        self.first_step = 0
        self.model_mode = False
        self._stop_model = threading.Event()  # the labeller asked the model to stop driving
        self._model_chosen: list[str] = []  # demos the model executed from this start
        self._passed_over: set[int] = set()  # starts the model tied, or R left, in model mode
        # Starts R left in this tab: not offered again while another start is free (else R
        # would swap between two ropes), then offered again.
        self._skipped: set[int] = set()
        self._in_step = False  # a drive step is simulating (outside the lock)
        self._placed_from: np.ndarray | None = None  # the rope the model's last state came from
        self._drive_version: str | None = None  # the model whose choices moved this rope
        self.model_failed: int | None = None  # rank of the model's failed choice in this state
        self.world = world if world is not None else RopeWorld()
        self._own_world = world is None
        self._simulate = simulate  # None: simulate tries in this process
        self.prefer: Callable[[], Sequence[int]] | None = None  # a suggested claiming order
        self._ahead: _ScanAhead | None = None  # the tried result's scan, started early
        self._lock = threading.RLock()
        self.phase = Phase.CHOOSING
        self.episode: EpisodeInfo | None = None
        self.task_id: str | None = None
        self.step_index = 0
        self.snapshot: SimSnapshot | None = None
        self.nodes_k3: np.ndarray | None = None  # the rope being labelled (before any try)
        self.cloud_n3: np.ndarray | None = None
        self.scan: ShownScan | None = None
        self.ranking: RankingModel = resources.current
        self.candidates: list[Candidate] = []
        self.selected: int | None = None
        self.rejected: set[int] = set()
        self.dead_ends: set[int] = set()
        self.last_try: TryResult | None = None
        self.message = ""
        self.rank_s = 0.0
        self.history: list[str] = []
        store.add_labeller(self.labeller, "human")

    # ------------------------------------------------------------------ views
    def view(self) -> SessionView:
        """A snapshot of what to draw."""
        with self._lock:
            return SessionView(
                phase=self.phase,
                labeller=self.labeller,
                task_id=self.task_id,
                step_index=self.step_index,
                max_steps=self.max_steps,
                rope_nodes_k3=self.nodes_k3,
                cloud_n3=self.cloud_n3,
                candidates=list(self.candidates),
                selected=self.selected,
                rejected=frozenset(self.rejected),
                model=self.ranking.label,
                last_try=self.last_try,
                message=self.message,
                rank_s=self.rank_s,
                history=list(self.history),
                dead_ends=frozenset(self.dead_ends),
                first_step=self.first_step,
                model_mode=self.model_mode,
                model_failed=self.model_failed,
                goal=self.res.task.description,
            )

    def candidate(self, rank: int) -> Candidate:
        """The candidate shown at ``rank`` (1-based)."""
        for c in self.candidates:
            if c.ranked.rank == rank:
                return c
        raise SessionError(f"no candidate ranked {rank} (ranks 1-{len(self.candidates)} shown)")

    # ------------------------------------------------------------------ episodes
    def start(self) -> SessionView:
        """Resume this labeller's unfinished episode, else claim the next unlabelled start."""
        with self._lock:
            opened = self.store.open_episode(self.labeller)
            if opened is not None:
                info, nodes = opened
                self._enter_episode(info, nodes)
                self.message = f"resumed your unfinished episode at step {info.n_labels + 1}"
                return self.view()
            return self._claim_next()

    def _claim_next(self) -> SessionView:
        info = self.store.start_episode(
            self.labeller,
            library_hash=self.res.library_hash,
            source="human",
            # The CPU kind whose numbers rank this episode's states: resumed on another kind,
            # a near-tie can rank two demos the other way (each label keeps what was shown).
            metadata={NUMERIC_KIND_KEY: numeric_kind()},
            prefer=self.prefer() if self.prefer is not None else (),
            overlap=self.res.overlap,
            exclude=sorted(self._skipped | (self._passed_over if self.model_mode else set())),
        )
        if info is None and self._skipped:  # only the starts R left are free: offer them again
            self._skipped.clear()
            return self._claim_next()
        if info is None:
            self.phase = Phase.NO_STARTS
            self.episode, self.snapshot, self.candidates = None, None, []
            self.nodes_k3, self.cloud_n3 = None, None
            self.message = "every training start is labelled or being labelled"
            return self.view()
        self._enter_episode(info, None)
        return self.view()

    def _enter_episode(self, info: EpisodeInfo, resume_nodes_k3: np.ndarray | None) -> None:
        self.episode = info
        state = self.store.get_state(info.start_state_id) if info.start_state_id else None
        self.task_id = None if state is None else state.provenance.task_id
        nodes = resume_nodes_k3
        if nodes is None:
            if state is None or state.rope_nodes_k3 is None:
                raise SessionError(f"episode {info.episode_id}: its start state has no rope")
            nodes = state.rope_nodes_k3
        self.world.reset(np.asarray(nodes, dtype=float))
        self.first_step = info.first_step
        self.max_steps = self.step_limit - info.first_step
        self.step_index = info.n_labels
        self._model_chosen = list(info.policy_chosen)
        self.history = [
            f"step {i + 1}: {key} (the model's choice)" for i, key in enumerate(info.policy_chosen)
        ]
        self._stop_model.clear()
        self._show_state()
        if self.model_mode and info.n_labels == 0 and info.first_step == 0 and self.candidates:
            self.phase = Phase.MODEL  # a fresh start: the model drives first
        if info.n_labels == 0 and info.policy_failed is not None:
            self._grey_model_failure(info.policy_failed)
        self._mark_stored_dead_ends()

    def _mark_stored_dead_ends(self) -> None:
        """The dead ends already stored in this state (before a reload or an undo), marked
        again: shown as dead ends and not offered first."""
        assert self.episode is not None
        step = self.first_step + self.step_index
        stored = set(self.store.dead_end_demos(self.episode.episode_id, step))
        marked = [c.ranked.rank for c in self.candidates if c.ranked.demo_key in stored]
        if not marked:
            return
        self.dead_ends.update(marked)
        self.rejected.update(marked)
        left = [c.ranked.rank for c in self.candidates if c.ranked.rank not in self.rejected]
        self.selected = left[0] if left else None

    def _grey_model_failure(self, demo_key: str) -> None:
        """The state the model reached, placed again: its failed choice greyed out as when
        it was handed over (the ranking is the same, bit for bit)."""
        failed = next((c for c in self.candidates if c.ranked.demo_key == demo_key), None)
        if failed is None:
            return
        self.rejected.add(failed.ranked.rank)
        self.model_failed = failed.ranked.rank
        left = [c.ranked.rank for c in self.candidates if c.ranked.rank not in self.rejected]
        self.selected = left[0] if left else None

    def _show_state(self) -> None:
        """Observe, scan and rank the world's current state (the greedy policy's ranking)."""
        t0 = time.perf_counter()
        self.ranking = self.res.current
        self.snapshot = self.world.snapshot()
        self.nodes_k3 = self.world.rope_nodes()
        featurizer = self.ranking.featurizer
        self.cloud_n3 = featurizer.observe(self.world)
        ahead, self._ahead = self._ahead, None
        if ahead is not None and ahead.fits(self.cloud_n3, self.ranking):
            phi, scan = ahead.result()  # scanned while the expert judged the try
        else:
            phi, scan = self._scan_state(self.cloud_n3)
        self.scan = scan
        ranked = rank_demos(scan, phi, self.ranking.model, self.res.library.keys, self.res.top_k)
        self.candidates = [self._candidate(r, scan) for r in ranked]
        self.selected = self.candidates[0].ranked.rank if self.candidates else None
        self.rejected = set()
        self.dead_ends = set()
        self.model_failed = None
        self.last_try = None
        self.phase = Phase.CHOOSING
        self.rank_s = time.perf_counter() - t0
        if not self.candidates:
            self.message = "no demo registers onto this rope: press R for another start"

    def _scan_state(self, cloud_n3: np.ndarray) -> tuple[np.ndarray | None, ShownScan]:
        """(phi or None, scan) of a state: one scanned lately from its kept scan; a start the
        shipped start scans hold from its summary, only its shown candidates registered (the
        full scan's numbers, bit for bit, on the CPU kind they were made on); any other state
        from a full scan."""
        featurizer = self.ranking.featurizer
        if featurizer.scanned_lately(cloud_n3):  # e.g. R back to a start shown a moment ago
            return _features(self.ranking, cloud_n3)
        quick = summary_scan(
            self.res.start_scans, featurizer, self.ranking.model, cloud_n3, self.res.top_k
        )
        return quick if quick is not None else _features(self.ranking, cloud_n3)

    def _candidate(self, ranked: RankedDemo, scan: ShownScan) -> Candidate:
        seg = self.res.library[ranked.demo_index]
        traj = seg.trajectory
        f = scan.f(ranked.demo_index)
        pos = f.evaluate(traj.positions_gt3.reshape(-1, 3)).reshape(traj.positions_gt3.shape)
        return Candidate(ranked, int(seg.step_index), pos, np.asarray(traj.closed_gt, bool))

    def warped_demo_cloud(self, rank: int) -> np.ndarray:
        """The candidate's demo cloud pushed onto the scene by its registration f."""
        with self._lock:
            cand = self.candidate(rank)
            assert self.scan is not None
            seg = self.res.library[cand.ranked.demo_index]
            return self.scan.f(cand.ranked.demo_index).evaluate(seg.pre_cloud_n3)

    # ------------------------------------------------------------------ selection
    def select(self, rank: int) -> SessionView:
        """Select the candidate at ``rank`` (the 3D pick and the list both call this)."""
        with self._lock:
            if self.phase is not Phase.CHOOSING:
                raise SessionError(f"cannot select while {self.phase.value}")
            self.candidate(rank)
            if rank in self.rejected:
                raise SessionError(f"candidate {rank} was rejected for this state")
            self.selected = rank
            self.message = ""
            return self.view()

    # ------------------------------------------------------------------ try and judge
    def try_selected(self, recorder: FrameRecorder | None = None) -> TryResult:
        """Simulate the selected candidate from the current state; the world keeps the result.

        ``recorder`` receives the execution's frames as they are simulated (for animation).
        """
        with self._lock:
            if self.phase is not Phase.CHOOSING:
                raise SessionError(f"cannot try while {self.phase.value}")
            if self.selected is None:
                raise SessionError("select a candidate first")
            if self.selected in self.rejected:
                raise SessionError(f"candidate {self.selected} was rejected; select another")
            cand = self.candidate(self.selected)
            self.phase = Phase.TRYING
            snapshot, cloud, nodes = self.snapshot, self.cloud_n3, self.nodes_k3
        result = self._execute(cand, snapshot, cloud, nodes, recorder, back_to=Phase.CHOOSING)
        with self._lock:
            if self.phase is not Phase.TRYING:  # the tab closed meanwhile: nothing to judge
                if self._own_world:
                    self.world.close()
                return result
            if result.acceptable and result.cloud_after_n3 is not None:
                self._ahead = _ScanAhead(result.cloud_after_n3, self.res.current)  # most are
            self.last_try = result
            self.phase = Phase.JUDGING
            self.message = _try_message(result)
        return result

    def _execute(
        self,
        cand: Candidate,
        snapshot: SimSnapshot | None,
        cloud: np.ndarray | None,
        nodes: np.ndarray | None,
        recorder: FrameRecorder | None,
        *,
        back_to: Phase,
    ) -> TryResult:
        """Simulate one candidate from the state shown (outside the lock); the world keeps the
        result. On an error the state is restored and the phase set to ``back_to``."""
        assert snapshot is not None and cloud is not None
        task = self.res.task
        stage_before = task.stage(nodes).stage if nodes is not None else 0
        t0 = time.perf_counter()
        rec = recorder if recorder is not None else FrameRecorder(FRAME_DT)
        try:
            if self._simulate is not None:  # in a worker process; then continue from its end
                outcome = self._simulate(snapshot, cloud, cand.ranked.demo_index, rec)
                self.world.restore(outcome.snapshot_after)
            else:
                self.world.restore(snapshot)
                outcome = self.res.agent.act(
                    self.world, cand.ranked.demo_index, cloud_n3=cloud, frames=rec
                )
            frames = outcome.execution.frames if outcome.execution is not None else None
            word: StepOutcome | FailureKind = (
                StepOutcome.KNOT
                if outcome.knot
                else (outcome.failure_kind or StepOutcome.PROGRESSED)
            )
            after = None if outcome.exploded else self.ranking.featurizer.observe(self.world)
        except Exception:
            with self._lock:
                self.world.restore(snapshot)
                if self.phase is not Phase.CLOSED:
                    self.phase = back_to
            raise
        return TryResult(
            cand.ranked.rank,
            cand.ranked.demo_key,
            outcome,
            frames,
            word,
            after,
            time.perf_counter() - t0,
            stage_before,
            task.stage_names,
        )

    # ------------------------------------------------------------------ the model drives
    def set_model_mode(self, on: bool) -> SessionView:
        """Turn "label where the model goes" on or off. On at a fresh start, the model drives it
        now; off while it drives, it stops after its current step (the expert labels there)."""
        with self._lock:
            self.model_mode = bool(on)
            fresh = self.step_index == 0 and self.first_step == 0 and not self.rejected
            if on and self.phase is Phase.CHOOSING and fresh and self.candidates:
                self._stop_model.clear()
                self.phase = Phase.MODEL
                self.message = (
                    f"the model drives this rope until its choice fails ({STOP_MODEL_KEY} stops it)"
                )
            elif not on and self.phase is Phase.MODEL:
                self._stop_model.set()
            return self.view()

    def stop_model(self) -> SessionView:
        """S: stop the model after its current step; the expert labels the state it reached."""
        with self._lock:
            if self.phase is not Phase.MODEL:
                raise SessionError("the model is not driving the rope")
            self._stop_model.set()
            self.message = "stopping the model after this step"
            return self.view()

    def drive_step(self, recorder: FrameRecorder | None = None) -> DriveOutcome:
        """Execute the model's first choice in the state shown, and advance or hand over."""
        with self._lock:
            if self.phase is not Phase.MODEL:
                return DriveOutcome.STOPPED
            if self._stop_model.is_set():
                self._hand_over(None, "you stopped the model")
                return DriveOutcome.HANDED_OVER
            if self._model_chosen and self._drive_version != self.ranking.version:
                # Another model ranks now (a retrain or a switch): the rollout so far is the
                # old model's, so the state is labelled as that model left it.
                self._hand_over(None, "the ranking model changed while it drove")
                return DriveOutcome.HANDED_OVER
            self._drive_version = self.ranking.version
            cand = self.candidates[0]
            snapshot, cloud, nodes = self.snapshot, self.cloud_n3, self.nodes_k3
            self._in_step = True
        try:
            result = self._execute(cand, snapshot, cloud, nodes, recorder, back_to=Phase.MODEL)
        finally:
            with self._lock:
                self._in_step = False
        with self._lock:
            if self.phase is not Phase.MODEL:
                if self.phase is Phase.CLOSED and self._own_world:
                    self.world.close()
                return DriveOutcome.STOPPED
            rollout_step = self.first_step + self.step_index
            if result.word == StepOutcome.KNOT:
                return self._model_tied_knot(result)
            advanced = result.acceptable and int(result.outcome.stage) > result.stage_before
            if not advanced or rollout_step + 1 >= self.step_limit:
                self.world.restore(self.snapshot)
                why = (
                    "its last step did not tie the knot"
                    if advanced
                    else f"#{result.rank} {result.demo_key}: {result.summary}"
                )
                self._hand_over(result.rank, f"the model's choice failed here ({why})")
                return DriveOutcome.HANDED_OVER
            self._model_chosen.append(result.demo_key)
            self.history.append(
                f"step {rollout_step + 1}: {result.demo_key} (the model's choice; "
                f"{result.stage_reached})"
            )
            # Placed from the nodes exactly as an accepted step is, so the state handed over
            # is one the store can place again bit for bit.
            self._placed_from = stored_nodes(result.outcome.nodes_after_k3)
            self.world.reset(self._placed_from)
            self.first_step += 1
            self.max_steps = self.step_limit - self.first_step
            self._show_state()
            if not self.candidates:
                self._hand_over(None, "no demo registers onto the rope the model reached")
                return DriveOutcome.HANDED_OVER
            if self._stop_model.is_set():
                self._hand_over(None, "you stopped the model")
                return DriveOutcome.HANDED_OVER
            self.phase = Phase.MODEL
            step = self.first_step + 1
            self.message = f"the model drives: step {step} ({STOP_MODEL_KEY} stops it)"
            return DriveOutcome.CONTINUES

    def _hand_over(self, failed_rank: int | None, why: str) -> None:
        """The expert labels the state shown: record how the model reached it (if it moved)."""
        assert self.episode is not None and self.nodes_k3 is not None
        self._stop_model.clear()
        self.phase = Phase.CHOOSING
        if self.first_step > 0:
            reached = {
                "policy": "greedy" if self._drive_version is not None else "nn",
                "model": self._drive_version,
                "step": self.first_step,
                "chosen_before": list(self._model_chosen),
                "start_task_id": self.task_id,
                "start_rope_hash": start_rope_hash(self._start_nodes()),  # as the CLI hashes it
                "labeller": self.labeller,
                "why": why,
                # greyed out again when the state is placed again (undo, resume)
                "failed_demo": None
                if failed_rank is None
                else self.candidate(failed_rank).ranked.demo_key,
            }
            assert self._placed_from is not None
            self.episode = self.store.mark_reached(
                self.episode.episode_id, self._placed_from, reached
            )
        if failed_rank is not None:  # it would fail the same way again
            self._grey_model_failure(self.candidate(failed_rank).ranked.demo_key)
        where = "this start" if self.first_step == 0 else f"step {self.first_step + 1}"
        self.message = f"{why}: label {where}"

    def _model_tied_knot(self, result: TryResult) -> DriveOutcome:
        """Nothing to label on a start the model solves: pass it over, claim the next."""
        assert self.episode is not None
        steps = self.first_step + 1
        task = self.task_id
        self._passed_over.add(int(self.episode.start_state_id or -1))
        old = self.episode
        self._claim_next()
        self.store.finish_episode(old.episode_id, status="abandoned")
        self.message = (
            f"the model tied the knot from {task} in {steps} steps: nothing to label there"
            + ("; next start" if self.episode is not None else "")
        )
        return DriveOutcome.TIED

    def _start_nodes(self) -> np.ndarray:
        """The rope nodes of the current episode's start: the task set's own (float64) when
        the start is one of its tasks, else the stored ones."""
        for task in self.res.tasks:
            if task.task_id == self.task_id:
                return task.start_nodes_k3
        assert self.episode is not None and self.episode.start_state_id is not None
        nodes = self.store.get_state(self.episode.start_state_id).rope_nodes_k3
        assert nodes is not None
        return nodes

    def accept(self) -> SessionView:
        """Y: store the label (state, choice, ranking shown, model, rope after) atomically."""
        with self._lock:
            result = self._judged()
            if not result.acceptable:
                raise SessionError(f"a {result.word} cannot be accepted: reject it (N) or F")
            assert self.episode is not None and self.cloud_n3 is not None
            step = LabelledStep(
                step_index=self.step_index,
                cloud_n3=self.cloud_n3,
                chosen_demo=result.demo_key,
                outcome=StepOutcome.KNOT
                if result.word == StepOutcome.KNOT
                else StepOutcome.PROGRESSED,
                rope_nodes_k3=self.nodes_k3,
                candidates=tuple(c.ranked.demo_key for c in self.candidates),
                candidate_scores_c=np.array([c.ranked.score for c in self.candidates]),
                model_version=self.ranking.version,
            )
            ends = result.word == StepOutcome.KNOT or self.step_index + 1 >= self.max_steps
            self.store.add_label(
                self.episode.episode_id,
                step,
                provenance=StateProvenance(self.task_id, self.first_step + self.step_index, None),
                next_nodes_k3=result.outcome.nodes_after_k3,
                finish=ends,  # the last label and the episode's end in one transaction
            )
            reached = result.stage_reached  # not "progressed": that is said of every execution
            shown = self.first_step + self.step_index + 1
            self.history.append(f"step {shown}: {result.demo_key} ({reached})")
            self.step_index += 1
            if ends:
                done = "knot tied" if result.word == StepOutcome.KNOT else "step limit reached"
                self._claim_next()
                self.message = f"episode done ({done}); next start loaded"
            else:
                # The next state is placed from the rope nodes just stored (at rest, as a resume
                # or an undo places it), so every state shown can be restored bit for bit and the
                # ranking stored with its label is the one the expert saw.
                self.world.reset(stored_nodes(result.outcome.nodes_after_k3))
                self._show_state()
                self.message = f"accepted {result.demo_key}; step {shown + 1}"
            return self.view()

    def reject(self) -> SessionView:
        """N: restore the state, grey the candidate out, select the next one."""
        with self._lock:
            result = self._judged()
            self._restore_after(result.rank)
            self.message = f"rejected {result.demo_key}"
            return self.view()

    def dead_end(self) -> SessionView:
        """F: store the state the try reached as a dead end, restore, select the next one."""
        with self._lock:
            result = self._judged()
            assert self.episode is not None
            if result.cloud_after_n3 is not None:
                self.store.add_dead_end(
                    self.episode.episode_id,
                    DeadEndState(result.cloud_after_n3, result.outcome.nodes_after_k3),
                    provenance=StateProvenance(
                        self.task_id, self.first_step + self.step_index, None
                    ),
                    demo_key=result.demo_key,  # shown again on a resume; stored once
                )
            self.dead_ends.add(result.rank)
            self._restore_after(result.rank)
            self.message = f"stored a dead end after {result.demo_key}"
            return self.view()

    def _judged(self) -> TryResult:
        if self.phase is not Phase.JUDGING or self.last_try is None:
            raise SessionError("try a candidate first (Enter)")
        return self.last_try

    def _restore_after(self, rank: int) -> None:
        assert self.snapshot is not None
        self.world.restore(self.snapshot)
        self.rejected.add(rank)
        self.last_try = None
        self.phase = Phase.CHOOSING
        left = [c.ranked.rank for c in self.candidates if c.ranked.rank not in self.rejected]
        self.selected = left[0] if left else None
        if not left:
            self.message = "every candidate was rejected: press R for a new start"

    def resample(self) -> SessionView:
        """R: abandon this rope's episode (its unsaved steps are dropped) and claim a new start."""
        with self._lock:
            if self.phase is Phase.TRYING:
                raise SessionError("wait for the try to finish")
            if self.phase is Phase.MODEL:
                raise SessionError(DRIVING_NOW)
            old = self.episode
            self.message = ""  # what was said about the old rope is not about the new one
            if old is not None and old.start_state_id is not None:
                # The model would drive it to the same state again: go on to other starts.
                # Without the model, the next R should not bring it straight back either.
                (self._passed_over if self.model_mode else self._skipped).add(old.start_state_id)
            # Claim the next start while this one is still held, so R never hands back the
            # rope just abandoned (unless it is the only one left).
            self._claim_next()
            if old is not None:
                self.store.finish_episode(old.episode_id, status="abandoned")
                if self.phase is Phase.NO_STARTS:
                    self._claim_next()
            return self.view()

    def undo(self) -> SessionView:
        """U: delete the last accepted label and go back to the state it was made in."""
        with self._lock:
            if self.phase is Phase.TRYING:
                raise SessionError("wait for the try to finish")
            if self.phase is Phase.MODEL:
                raise SessionError(DRIVING_NOW)
            if self.episode is None or self.store.episode(self.episode.episode_id).n_labels == 0:
                # A finished episode stays finished: undoing into it would silently abandon
                # the rope on screen. Said in the status area, where the labeller looks.
                self.message = "nothing to undo on this rope: no step of it has been accepted yet"
                return self.view()
            undone = self.store.undo_last_label(self.labeller)
            if undone is None:
                raise SessionError("nothing to undo")
            if self.episode is not None and self.episode.episode_id != undone.episode_id:
                self._release_if_unlabelled()
            opened = self.store.open_episode(self.labeller)
            assert opened is not None, "undo reopens the label's episode"
            self._enter_episode(*opened)
            self.message = f"undid step {undone.step_index + 1} ({undone.chosen_demo})"
            return self.view()

    def _release_if_unlabelled(self) -> None:
        """Abandon the current episode when it holds no label, so its start can be claimed."""
        if self.episode is not None and self.store.episode(self.episode.episode_id).n_labels == 0:
            self.store.finish_episode(self.episode.episode_id, status="abandoned")

    def detach(self) -> SessionView:
        """Another tab of this labeller took the episode over: stop here, keep the episode open
        (nothing is released or abandoned), say so."""
        with self._lock:
            was = self.phase
            self.phase = Phase.CLOSED
            self.message = "this episode was taken over in another tab; reload to label here"
            busy = was is Phase.TRYING or (was is Phase.MODEL and self._in_step)
            if self._own_world and not busy:  # else the running step closes it when done
                self.world.close()
            return self.view()

    def close(self) -> None:
        """The tab went away: drop any try; release the start if nothing was accepted on it."""
        with self._lock:
            was = self.phase
            self.phase = Phase.CLOSED
            if was is not Phase.NO_STARTS:
                self._release_if_unlabelled()
            busy = was is Phase.TRYING or (was is Phase.MODEL and self._in_step)
            if self._own_world and not busy:  # else the running step closes it when done
                self.world.close()


def stored_nodes(nodes_k3: np.ndarray) -> np.ndarray:
    """Rope nodes exactly as the store gives them back (its JSON round trip of float64)."""
    return np.asarray(np.asarray(nodes_k3, dtype=float).tolist(), dtype=float)


def _features(ranking: RankingModel, cloud_n3: np.ndarray):
    """(phi or None, scan) of a cloud for a ranking model (no features without a model)."""
    if ranking.model is not None:
        return ranking.featurizer.features(cloud_n3)
    return None, ranking.featurizer.scan(cloud_n3)


class _ScanAhead:
    """The scan of a try's resulting rope, run on a thread while the expert judges the try.

    Used only if the next state is exactly that cloud ranked by the same model; otherwise
    dropped (a rejected try, a model switch).
    """

    def __init__(self, cloud_n3: np.ndarray, ranking: RankingModel) -> None:
        self.cloud_n3 = np.array(cloud_n3)
        self.ranking = ranking
        self._out: list = []
        self._thread = threading.Thread(target=self._run, name="scan-ahead", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        try:
            self._out.append(_features(self.ranking, self.cloud_n3))
        except Exception as exc:  # the state is then scanned again in the foreground
            self._out.append(exc)

    def fits(self, cloud_n3: np.ndarray, ranking: RankingModel) -> bool:
        """True when this scan is of ``cloud_n3`` under ``ranking``."""
        return ranking is self.ranking and np.array_equal(cloud_n3, self.cloud_n3)

    def result(self):
        """(phi, scan), waiting for the thread; recomputed here if it failed."""
        self._thread.join()
        out = self._out[0]
        if isinstance(out, Exception):
            return _features(self.ranking, self.cloud_n3)
        return out


def _try_message(result: TryResult) -> str:
    if result.word == StepOutcome.KNOT:
        return f"{result.demo_key} tied the knot: Y to accept"
    if result.word == StepOutcome.PROGRESSED:
        return f"{result.demo_key}: {result.summary}; Y accept, N reject, F dead end"
    return f"{result.demo_key}: {result.word}; N to reject or F to mark a dead end"

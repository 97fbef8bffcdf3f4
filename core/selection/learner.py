"""Max-margin Q-learning with Bellman constraints (the paper's learner), solved as a QP in cvxpy.

Shape suffixes: a = actions (library demos), d = feature dimension, s = labelled expert states.

Q(s, a) = w . phi(s, a) + w0 with phi standardised column-wise (indicator columns left as 0/1).
The QP (docs/reference/learning.md, "The QP", with the changes listed below):

    minimise   ||w||^2 + C sum_s xi_s + D (sum_k |e_k| + sum_f yd_f)
    subject to Q(s, a*) >= Q(s, a) + kappa * m(a*, a) - xi_s       every expert state s, a != a*
               Q(s_t, a*_t) = -1 + gamma Q(s_t+1, a*_t+1) + e_k     consecutive expert steps
               Q(s_T, a*_T) = -1 + goal_reward + e_k                 the step that tied the knot
               Q(s_f, a) <= dead_end_value + yd_f                    every dead end f, every a
               xi, yd >= 0

Changes from the original, and why:
- w0 is a real variable in the Bellman, goal and dead-end rows (the original left it undetermined),
  so values can sit at the Bellman targets without spending ||w||^2 on a constant.
- Scale mismatch: margins m are metres (mean closest-point distance between warped gripper
  trajectories, typically 0.0-0.3) while Bellman targets are in steps (9, 8, ..., -10). We convert
  metres to value units with kappa = margin_scale / median(positive margins in the training set),
  so the typical wrong action must lose by ``margin_scale`` value units (default 1 = one step).
  kappa is stored in the model.
- Features are standardised on the training set so ||w||^2 regularises every column equally.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, fields
from typing import Protocol

import numpy as np
from scipy import sparse

from knotlab.core.arrays import finite_matrix
from knotlab.core.errors import InvalidInputError, SolverError
from knotlab.core.outcomes import StepOutcome
from knotlab.core.selection.labels import LabelledExecution
from knotlab.core.selection.qmodel import QModel


@dataclass(frozen=True, eq=False)
class LabelledState:
    """Features of every action in one expert state, the expert's action and its margins."""

    phi_ad: np.ndarray  # (A, d)
    expert_action: int
    margins_a: np.ndarray  # (A,) metres, m(a*, a); 0 at a*
    execution: int = 0  # which execution it came from
    step: int = 0  # step index within that execution
    # Actions known to do as well as the expert's here (tried in simulation): no margin row
    # against them, since the label does not prefer the expert's demo over them.
    also_good_a: np.ndarray | None = None

    def __post_init__(self) -> None:
        phi = finite_matrix("phi_ad", self.phi_ad)
        margins = np.asarray(self.margins_a, dtype=float)
        if margins.shape != (phi.shape[0],):
            raise InvalidInputError(
                f"margins_a must have shape ({phi.shape[0]},), got {margins.shape}"
            )
        if not np.all(np.isfinite(margins)) or np.any(margins < 0):
            raise InvalidInputError("margins_a must be finite and non-negative")
        if not 0 <= self.expert_action < phi.shape[0]:
            raise InvalidInputError(
                f"expert_action {self.expert_action} out of range for {phi.shape[0]} actions"
            )
        object.__setattr__(self, "phi_ad", phi)
        object.__setattr__(self, "margins_a", margins)
        if self.also_good_a is not None:
            good = np.asarray(self.also_good_a, dtype=bool)
            if good.shape != (phi.shape[0],):
                raise InvalidInputError(
                    f"also_good_a must have shape ({phi.shape[0]},), got {good.shape}"
                )
            object.__setattr__(self, "also_good_a", good)


@dataclass(frozen=True, eq=False)
class TrainingData:
    """Everything the QP needs: expert states, Bellman links, goal steps and dead ends."""

    states: tuple[LabelledState, ...]
    bellman_pairs: tuple[tuple[int, int], ...] = ()  # (state i, next state j) along an execution
    goal_states: tuple[int, ...] = ()  # states whose expert action produced the knot
    dead_ends_phi: tuple[np.ndarray, ...] = ()  # (A, d) features of every action in a dead end

    def __post_init__(self) -> None:
        if not self.states and not self.dead_ends_phi:
            raise InvalidInputError("TrainingData needs at least one labelled state or dead end")
        # An execution the expert could not finish still contributes its dead ends.
        d = (self.states[0].phi_ad if self.states else np.asarray(self.dead_ends_phi[0])).shape[1]
        for i, s in enumerate(self.states):
            if s.phi_ad.shape[1] != d:
                raise InvalidInputError(f"state {i} has {s.phi_ad.shape[1]} features, expected {d}")
        n = len(self.states)
        for i, j in self.bellman_pairs:
            if not (0 <= i < n and 0 <= j < n):
                raise InvalidInputError(f"Bellman pair ({i}, {j}) refers to a missing state")
        for g in self.goal_states:
            if not 0 <= g < n:
                raise InvalidInputError(f"goal state {g} refers to a missing state")
        dead = tuple(finite_matrix("dead-end phi", p) for p in self.dead_ends_phi)
        for p in dead:
            if p.shape[1] != d:
                raise InvalidInputError(
                    f"dead-end features have {p.shape[1]} columns, expected {d}"
                )
        object.__setattr__(self, "dead_ends_phi", dead)

    @property
    def n_features(self) -> int:
        """Feature dimension d."""
        return int((self.states[0].phi_ad if self.states else self.dead_ends_phi[0]).shape[1])


class StateFeaturizer(Protocol):
    """Computes phi(s, .) for every action from an observed cloud, and expert margins."""

    def features(self, cloud_n3: np.ndarray) -> tuple[np.ndarray, object]:
        """phi_ad for every demo in the library, plus whatever the margins need (the scan)."""
        ...

    def margins(self, scan: object, expert_action: int) -> np.ndarray:
        """m(a*, a) in metres for every action a, given the scan of the same state."""
        ...

    def action_index(self, demo_key: str) -> int:
        """Row of ``demo_key`` in phi_ad."""
        ...

    def spec(self) -> dict:
        """JSON-able description of the features (saved with the model)."""
        ...


def build_training_data(
    executions: Sequence[LabelledExecution],
    featurizer: StateFeaturizer,
    progress: Callable[[int], None] | None = None,
) -> TrainingData:
    """Turn labelled executions into QP inputs: one scan per labelled state and per dead end."""
    states: list[LabelledState] = []
    pairs: list[tuple[int, int]] = []
    goals: list[int] = []
    dead: list[np.ndarray] = []
    for e_idx, execution in enumerate(executions):
        prev: int | None = None
        for step in execution.steps:
            if step.outcome == StepOutcome.SKIPPED:
                prev = None
                continue
            phi_ad, scan = featurizer.features(step.cloud_n3)
            a_star = featurizer.action_index(step.chosen_demo)
            margins = featurizer.margins(scan, a_star)
            states.append(LabelledState(phi_ad, a_star, margins, e_idx, step.step_index))
            idx = len(states) - 1
            if prev is not None:
                pairs.append((prev, idx))
            if step.outcome == StepOutcome.KNOT:
                goals.append(idx)
                prev = None
            elif step.outcome in (StepOutcome.DEAD_END, StepOutcome.MISGRASP):
                # The chosen action led nowhere useful: no Bellman link out of it.
                prev = None
            else:
                prev = idx
        for dead_end in execution.dead_ends:
            phi_ad, _ = featurizer.features(dead_end.cloud_n3)
            dead.append(phi_ad)
        if progress is not None:
            progress(1)
    return TrainingData(tuple(states), tuple(pairs), tuple(goals), tuple(dead))


CLARABEL_MAX_ITER = 1000


@dataclass
class MaxMarginQLearner:
    """Fits a QModel by max-margin structured prediction plus Bellman (ALP) constraints."""

    C: float = 1.0
    D: float = 1.0
    gamma: float = 1.0
    step_reward: float = -1.0
    goal_reward: float = 10.0
    dead_end_value: float = -10.0
    margin_scale: float = 1.0
    standardize: bool = True
    hard_bellman: bool = False  # equality without slack (can make the QP infeasible)
    solver: str = "CLARABEL"
    solver_options: dict = field(default_factory=dict)
    verbose: bool = False

    def fit(
        self,
        data: TrainingData | Sequence[LabelledExecution],
        featurizer: StateFeaturizer | None = None,
    ) -> QModel:
        """Solve the QP on labelled data (or executions, featurised by ``featurizer``).

        Hyper-parameters live in the constructor, data here (scikit-learn style). The
        featurizer's spec (column names, indicator columns, landmarks) is saved in the model, so
        pass it whenever the data came from one.
        """
        if not isinstance(data, TrainingData):
            if featurizer is None:
                raise InvalidInputError(
                    "fit(executions) needs a featurizer to compute features: "
                    "fit(executions, featurizer)"
                )
            data = build_training_data(list(data), featurizer)
        self._check_hyperparameters()
        if not data.states:
            raise InvalidInputError(
                "fit needs at least one labelled expert state, not only dead ends"
            )
        spec = featurizer.spec() if featurizer is not None else {}
        indicator = np.asarray(spec.get("indicator_mask", []), dtype=bool)
        mean_d, scale_d = _standardisation(data, indicator, self.standardize)
        kappa = _margin_factor(data, self.margin_scale)

        t0 = time.perf_counter()
        w, w0, info = self._solve(data, mean_d, scale_d, kappa)
        solve_s = time.perf_counter() - t0
        self.coef_ = w
        self.intercept_ = w0
        self.margin_factor_ = kappa
        metrics = _training_metrics(data, w, w0, mean_d, scale_d, self.step_reward, self.gamma)
        metrics.update(info, solve_seconds=solve_s, margin_factor=kappa)
        hyper = {
            f.name: getattr(self, f.name)
            for f in fields(self)
            if f.name not in ("verbose", "solver_options")
        }
        landmarks = getattr(featurizer, "landmarks", None)
        self.model_ = QModel(w, w0, mean_d, scale_d, spec, hyper, metrics, landmarks)
        return self.model_

    def _options(self) -> dict:
        """The solver's options: CLARABEL's iteration cap raised above its default."""
        # CLARABEL stops at 200 interior-point iterations by default; pooled label sets of a few
        # thousand states (over 300,000 margin rows) can need more. A fit that converges under
        # 200 takes the same iterations either way, so its model is unchanged.
        if self.solver == "CLARABEL":
            return {"max_iter": CLARABEL_MAX_ITER, **self.solver_options}
        return dict(self.solver_options)

    def _check_hyperparameters(self) -> None:
        for name in ("C", "D", "margin_scale"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise InvalidInputError(f"{name} must be finite and >= 0, got {value}")

    def _solve(
        self, data: TrainingData, mean_d: np.ndarray, scale_d: np.ndarray, kappa: float
    ) -> tuple[np.ndarray, float, dict]:
        import cvxpy as cp  # deferred: cvxpy import costs ~1 s and only fitting needs it

        d = data.n_features
        std = lambda phi: (phi - mean_d) / scale_d  # noqa: E731
        w = cp.Variable(d, name="w")
        w0 = cp.Variable(name="w0")
        n_s = len(data.states)
        xi = cp.Variable(n_s, nonneg=True, name="xi")
        objective = cp.sum_squares(w) + self.C * cp.sum(xi)
        constraints = []

        # Margin rows: (phi(s,a) - phi(s,a*)) w + kappa m(a*,a) - xi_s <= 0 for a != a*.
        rows, rhs, owner = [], [], []
        expert_phi = np.empty((n_s, d))
        for i, s in enumerate(data.states):
            phi = std(s.phi_ad)
            expert_phi[i] = phi[s.expert_action]
            others = np.arange(phi.shape[0]) != s.expert_action
            if s.also_good_a is not None:
                others &= ~s.also_good_a
            rows.append(phi[others] - phi[s.expert_action])
            rhs.append(kappa * s.margins_a[others])
            owner.append(np.full(int(others.sum()), i))
        # Sparse: state-only columns (phase, landmarks) cancel in these differences and the
        # one-hots leave two entries per row, so most of the matrix is exact zeros.
        diff = sparse.csr_matrix(np.concatenate(rows))
        if diff.shape[0]:
            constraints.append(diff @ w + np.concatenate(rhs) - xi[np.concatenate(owner)] <= 0)

        # Bellman and goal rows: Q(s, a*) - target = e, L1-penalised (or hard).
        q_expert = expert_phi @ w + w0
        residuals = []
        if data.bellman_pairs:
            i_idx = np.array([p[0] for p in data.bellman_pairs])
            j_idx = np.array([p[1] for p in data.bellman_pairs])
            residuals.append(q_expert[i_idx] - (self.step_reward + self.gamma * q_expert[j_idx]))
        if data.goal_states:
            g_idx = np.array(data.goal_states)
            residuals.append(q_expert[g_idx] - (self.step_reward + self.goal_reward))
        for r in residuals:
            if self.hard_bellman:
                constraints.append(r == 0)
            else:
                objective = objective + self.D * cp.norm1(r)

        # Dead ends: every action's value at most dead_end_value (+ one slack per state).
        if data.dead_ends_phi:
            n_f = len(data.dead_ends_phi)
            yd = cp.Variable(n_f, nonneg=True, name="yd")
            dead_std = [std(p) for p in data.dead_ends_phi]
            dead_owner = np.concatenate([np.full(p.shape[0], f) for f, p in enumerate(dead_std)])
            # Columns equal for every action of a state (phase, landmarks) enter once per dead
            # end instead of once per (dead end, action) row: same constraints, far fewer
            # non-zeros (70 landmarks x 150 actions x 270 dead ends would be 2.8 M).
            state_col = np.logical_and.reduce([np.all(p == p[0], axis=0) for p in dead_std])
            state_idx, action_idx = np.flatnonzero(state_col), np.flatnonzero(~state_col)
            dead_action = sparse.csr_matrix(np.concatenate([p[:, action_idx] for p in dead_std]))
            value = dead_action @ w[action_idx] + w0 - yd[dead_owner]
            if state_idx.size:
                dead_state = np.stack([p[0, state_idx] for p in dead_std])
                value = value + (dead_state @ w[state_idx])[dead_owner]
            constraints.append(value <= self.dead_end_value)
            objective = objective + self.D * cp.sum(yd)

        problem = cp.Problem(cp.Minimize(objective), constraints)
        try:
            with warnings.catch_warnings():
                # An inaccurate solve is reported below as a SolverError naming the status.
                warnings.simplefilter("ignore", UserWarning)
                problem.solve(solver=self.solver, verbose=self.verbose, **self._options())
        except cp.error.SolverError as exc:
            raise SolverError(f"QP solver {self.solver} failed: {exc}") from exc
        if problem.status not in (cp.OPTIMAL,):
            raise SolverError(
                f"QP solver {self.solver} ended with status {problem.status!r} "
                f"({n_s} states, {diff.shape[0]} margin rows, "
                f"{len(data.bellman_pairs)} Bellman rows, {len(data.dead_ends_phi)} dead ends)"
            )
        w_val = np.asarray(w.value, dtype=float)
        # With margin rows only, w0 cancels everywhere and the solver leaves it unset: any value
        # is optimal, so take 0 (the original left it undetermined too).
        w0_val = float(w0.value) if w0.value is not None else 0.0
        if not (np.all(np.isfinite(w_val)) and np.isfinite(w0_val)):
            raise SolverError(f"QP solver {self.solver} returned non-finite weights")
        info = {
            "status": problem.status,
            "objective": float(problem.value),
            "n_states": n_s,
            "n_margin_rows": int(diff.shape[0]),
            "n_bellman_rows": len(data.bellman_pairs) + len(data.goal_states),
            "n_dead_ends": len(data.dead_ends_phi),
            "n_variables": int(sum(v.size for v in problem.variables())),
        }
        return w_val, w0_val, info


def _standardisation(
    data: TrainingData, indicator_d: np.ndarray, enabled: bool
) -> tuple[np.ndarray, np.ndarray]:
    """Column mean and scale over all training rows; indicator columns keep mean 0, scale 1."""
    d = data.n_features
    if not enabled:
        return np.zeros(d), np.ones(d)
    stacked = np.concatenate([s.phi_ad for s in data.states] + list(data.dead_ends_phi))
    mean = stacked.mean(axis=0)
    scale = stacked.std(axis=0)
    scale[scale < 1e-12] = 1.0  # constant columns: leave them be rather than divide by ~0
    if indicator_d.size == d:
        mean[indicator_d] = 0.0
        scale[indicator_d] = 1.0
    return mean, scale


def _margin_factor(data: TrainingData, margin_scale: float) -> float:
    """kappa: metres -> value units, so the median positive margin is worth ``margin_scale``."""
    positive = np.concatenate([s.margins_a[s.margins_a > 0] for s in data.states])
    if positive.size == 0:
        return 0.0
    return float(margin_scale / np.median(positive))


def _training_metrics(
    data: TrainingData,
    w: np.ndarray,
    w0: float,
    mean_d: np.ndarray,
    scale_d: np.ndarray,
    step_reward: float,
    gamma: float,
) -> dict:
    """How well the fitted Q reproduces the expert: top-1 accuracy, expert rank, Bellman error."""
    ranks = []
    q_expert = []
    for s in data.states:
        q = ((s.phi_ad - mean_d) / scale_d) @ w + w0
        q_expert.append(q[s.expert_action])
        ranks.append(int(np.sum(q > q[s.expert_action])))
    ranks_arr = np.asarray(ranks)
    out = {
        "train_top1": float(np.mean(ranks_arr == 0)),
        "train_mean_expert_rank": float(ranks_arr.mean()),
    }
    if data.bellman_pairs:
        qe = np.asarray(q_expert)
        err = [qe[i] - (step_reward + gamma * qe[j]) for i, j in data.bellman_pairs]
        out["bellman_mean_abs_error"] = float(np.mean(np.abs(err)))
    return out

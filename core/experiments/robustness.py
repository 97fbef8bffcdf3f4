"""The robustness study's vocabulary and arithmetic: which worlds it runs, and how each compares
with the matched world, task by task.

A study setting is a world (`core/world/mismatch.py`) and a state estimator
(`core/world/estimate.py`); the agent's model is the nominal world (the one its library and
Q-model were made in), which measures the rope's length (and with ``:measured`` its radius) at
the start, or in a control the world's own physics. Outcomes are compared with the matched
world's outcomes of the same policy on the same tasks: how many tasks the mismatch lost
(knotted when matched, not here) and gained, with an exact two-sided sign test on those
discordant tasks.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from scipy.stats import binomtest

from knotlab.core.errors import InvalidInputError
from knotlab.core.experiments.bench.report import wilson_interval
from knotlab.core.world.estimate import EstimatorKind
from knotlab.core.world.mismatch import MismatchFactor, family_settings, parse_setting


@dataclass(frozen=True)
class StudySetting:
    """One world of the study: its physics setting's name and the agent's state estimator."""

    name: str  # the results folder's name, e.g. "combined25", "mass-50", "tracker"
    world: str  # a physics setting name (`mismatch.parse_setting`)
    estimator: EstimatorKind = EstimatorKind.PERFECT
    # The agent's model: "nominal", the world's own setting (a control: the same world with a
    # model that knows it, so what is left of a loss is the world being unlike the demos'), or
    # "measured" (nominal, but measuring the rope's radius from the first cloud, as its length).
    agent_model: str = "nominal"

    @property
    def factor(self) -> MismatchFactor | None:
        """The one factor this setting changes (None: nominal, combined, the trackers)."""
        return parse_setting(self.world).factor

    @property
    def level(self) -> float:
        """The mismatch level as a fraction (0 for nominal and the trackers)."""
        setting = parse_setting(self.world)
        if setting.per_task:
            return setting.combined_level
        return abs(setting.scale - 1.0)


_TRACKERS = tuple(kind.value for kind in EstimatorKind if kind is not EstimatorKind.PERFECT)


def parse_study_settings(text: str) -> list[StudySetting]:
    """Settings from a comma list: nominal, the trackers (tracker, video, tracker_ends,
    video_ends, tracker_marked, video_marked), combinedPCT, FACTOR+PCT, FACTOR-PCT,
    familiesPCT (every factor at +PCT and -PCT where that is a possible world), or any world
    followed by ``:known`` (the agent's model is that world's own physics: a control) or
    ``:measured`` (the nominal model measuring the rope's radius too)."""
    out: list[StudySetting] = []
    for item in (part.strip() for part in text.split(",")):
        if not item:
            continue
        if item in _TRACKERS:
            out.append(StudySetting(item, "nominal", EstimatorKind(item)))
        elif item.endswith(":known"):
            world = item.removesuffix(":known")
            parse_setting(world)
            out.append(StudySetting(f"{world}_known", world, agent_model=world))
        elif item.endswith(":measured"):
            world = item.removesuffix(":measured")
            parse_setting(world)
            out.append(StudySetting(f"{world}_measured", world, agent_model="measured"))
        elif item.startswith("families"):
            try:
                pct = float(item.removeprefix("families"))
            except ValueError:
                raise InvalidInputError(
                    f"{item!r}: expected familiesPCT, e.g. families25"
                ) from None
            out += [
                StudySetting(name, name)
                for factor in MismatchFactor
                for name in family_settings(factor, (pct,))
            ]
        else:
            parse_setting(item)  # a one-line error for an unknown name, now
            out.append(StudySetting(item, item))
    if not out:
        raise InvalidInputError("no study settings given")
    return list({s.name: s for s in out}.values())


@dataclass(frozen=True)
class PairedRow:
    """One policy in one setting against the matched world, on the tasks both ran."""

    setting: str
    policy: str
    n: int
    successes: int
    matched_successes: int
    lost: int  # knotted in the matched world, not here
    gained: int  # knotted here, not in the matched world
    p_value: float  # exact two-sided sign test on the lost and gained tasks
    errored: int  # episodes that errored (then the row is not a result)

    @property
    def rate(self) -> float:
        """Success rate here."""
        return self.successes / self.n if self.n else math.nan

    @property
    def matched_rate(self) -> float:
        """Success rate in the matched world on the same tasks."""
        return self.matched_successes / self.n if self.n else math.nan

    @property
    def wilson(self) -> tuple[float, float]:
        """Wilson 95 % interval of the rate here."""
        return wilson_interval(self.successes, self.n)

    @property
    def change_points(self) -> float:
        """Percentage points gained (+) or lost (-) against the matched world."""
        return 100.0 * (self.rate - self.matched_rate)


def paired_row(
    setting: str, policy: str, here: Sequence[dict], matched: Mapping[str, dict]
) -> PairedRow:
    """Compare one policy's outcomes in a setting with its matched-world outcomes by task id."""
    common = [r for r in here if r["task_id"] in matched]
    ok = [bool(r["success"]) for r in common]
    ok_matched = [bool(matched[r["task_id"]]["success"]) for r in common]
    lost = sum(m and not h for h, m in zip(ok, ok_matched, strict=True))
    gained = sum(h and not m for h, m in zip(ok, ok_matched, strict=True))
    p = binomtest(lost, lost + gained).pvalue if lost + gained else 1.0
    return PairedRow(
        setting,
        policy,
        len(common),
        sum(ok),
        sum(ok_matched),
        lost,
        gained,
        float(p),
        sum(r.get("failure_kind") == "error" for r in common),
    )


def worst_factors(rows: Sequence[PairedRow]) -> dict[str, tuple[str, float]]:
    """For each policy, the single-factor setting that cost it the most points (and how many).

    Only settings run on as many tasks as the most of their level (the same size of mismatch)
    for that policy compete: a setting still part-run has a few tasks whose change ranks by
    chance (one task lost of two is -50 points).
    """
    single: list[tuple[PairedRow, float]] = []
    for row in rows:
        try:
            setting = parse_setting(row.setting)
        except InvalidInputError:
            continue  # the tracker, a control
        if setting.factor is None or row.n == 0:
            continue
        single.append((row, round(abs(setting.scale - 1.0), 6)))
    most: dict[tuple[str, float], int] = {}
    for row, level in single:
        most[(row.policy, level)] = max(most.get((row.policy, level), 0), row.n)
    worst: dict[str, tuple[str, float]] = {}
    for row, level in single:
        if row.n < most[(row.policy, level)]:
            continue
        if row.policy not in worst or row.change_points < worst[row.policy][1]:
            worst[row.policy] = (row.setting, row.change_points)
    return worst

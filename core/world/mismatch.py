"""The world that executes and the model an agent simulates with, as named, seeded settings.

A `PhysicsParams` is everything physical about a rope world (`RopeParams` and `GripperParams`).
A `PhysicsSetting` says how one is made from the nominal world (the world the library's demos,
the Q-model and every result before this module were made in):

- ``nominal``: the nominal world itself;
- ``<factor><sign><percent>`` (``mass+25``, ``table_friction-50``): one factor scaled by
  1 +- percent/100, everything else nominal;
- ``combined<percent>`` (``combined25``): every factor scaled by its own draw from
  U(1 - p, 1 + p), drawn per task from a generator seeded by (setting seed, task id), so the same
  task always meets the same world and every policy meets it;
- a JSON file ``{"rope": {...}, "gripper": {...}}`` of absolute values (fields left out stay
  nominal).

The factors (`MismatchFactor`) and what each scales are in docs/robustness.md. Friction is split
the way PyBullet combines it (the product of the two bodies' coefficients): ``table_friction``
scales the table's coefficient, so rope-on-table friction and nothing else; ``rope_friction``
scales the rope's by sqrt(s) and the table's by 1/sqrt(s), so rope-on-rope friction by s and
rope-on-table not at all.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import asdict, dataclass, field, fields, replace
from enum import StrEnum
from pathlib import Path

import numpy as np

from knotlab.core.errors import InvalidInputError
from knotlab.core.seeds import text_seed
from knotlab.core.world.sim import GripperParams, RopeParams


@dataclass(frozen=True)
class PhysicsParams:
    """Everything physical about a rope world: the rope and solver, and the grippers."""

    rope: RopeParams = field(default_factory=RopeParams)
    gripper: GripperParams = field(default_factory=GripperParams)

    def to_dict(self) -> dict:
        """JSON-able ``{"rope": {...}, "gripper": {...}}`` (every field)."""
        return {"rope": asdict(self.rope), "gripper": asdict(self.gripper)}

    @classmethod
    def from_dict(cls, data: object, where: str = "physics parameters") -> PhysicsParams:
        """Nominal values overridden by ``data``'s ``rope`` and ``gripper`` objects (one-line
        error naming an unknown section or field, or a bad value)."""
        if not isinstance(data, dict):
            raise InvalidInputError(f"{where}: expected a JSON object with 'rope' and 'gripper'")
        unknown = set(data) - {"rope", "gripper"}
        if unknown:
            raise InvalidInputError(
                f"{where}: unknown section {sorted(unknown)[0]!r}; expected 'rope' and 'gripper'"
            )
        parts: dict[str, object] = {}
        for section, kind in (("rope", RopeParams), ("gripper", GripperParams)):
            given = data.get(section, {})
            if not isinstance(given, dict):
                raise InvalidInputError(f"{where}: {section!r} must be a JSON object")
            names = {f.name for f in fields(kind)}
            bad = set(given) - names
            if bad:
                raise InvalidInputError(
                    f"{where}: {section} has no field {sorted(bad)[0]!r} "
                    f"(fields: {', '.join(sorted(names))})"
                )
            try:
                parts[section] = kind(**given)
            except (TypeError, ValueError) as exc:
                raise InvalidInputError(f"{where}: {exc}") from None
        return cls(parts["rope"], parts["gripper"])


NOMINAL = PhysicsParams()


class MismatchFactor(StrEnum):
    """One physical factor a world can differ in from the agent's model of it."""

    TABLE_FRICTION = "table_friction"  # rope-on-table friction
    ROPE_FRICTION = "rope_friction"  # rope-on-rope friction
    MASS = "mass"
    DAMPING = "damping"  # linear and angular damping together
    RADIUS = "radius"
    LENGTH = "length"
    GRASP_REACH = "grasp_reach"  # how far from a link a closing gripper still catches it
    GRIP_FORCE = "grip_force"  # below what the rope's drag needs, the grasp slips (lags)
    GRIPPER_SPEED = "gripper_speed"  # both speed caps
    SETTLE_TIME = "settle_time"


def scale_factor(params: PhysicsParams, factor: MismatchFactor, scale: float) -> PhysicsParams:
    """``params`` with one factor multiplied by ``scale`` (> 0); a one-line error where the
    result is not a valid rope (a radius whose diameter exceeds the link length)."""
    if not (math.isfinite(scale) and scale > 0):
        raise InvalidInputError(f"a mismatch scale must be positive, got {scale}")
    rope, grip = params.rope, params.gripper
    table = rope.friction if rope.table_friction is None else rope.table_friction
    try:
        if factor is MismatchFactor.TABLE_FRICTION:
            rope = replace(rope, table_friction=table * scale)
        elif factor is MismatchFactor.ROPE_FRICTION:
            root = math.sqrt(scale)
            rope = replace(rope, friction=rope.friction * root, table_friction=table / root)
        elif factor is MismatchFactor.MASS:
            rope = replace(rope, mass=rope.mass * scale)
        elif factor is MismatchFactor.DAMPING:
            rope = replace(
                rope,
                linear_damping=rope.linear_damping * scale,
                angular_damping=rope.angular_damping * scale,
            )
        elif factor is MismatchFactor.RADIUS:
            rope = replace(rope, radius=rope.radius * scale)
        elif factor is MismatchFactor.LENGTH:
            # 40 links of a shorter rope are shorter than its diameter: thinned to fit them.
            length = rope.length * scale
            fit = 0.5 * length / rope.n_links * (1 - 1e-9)
            rope = replace(rope, length=length, radius=min(rope.radius, fit))
        elif factor is MismatchFactor.GRASP_REACH:
            grip = replace(grip, grasp_radius=grip.grasp_radius * scale)
        elif factor is MismatchFactor.GRIP_FORCE:
            grip = replace(grip, grip_force=grip.grip_force * scale)
        elif factor is MismatchFactor.GRIPPER_SPEED:
            grip = replace(
                grip,
                max_speed=grip.max_speed * scale,
                max_descent_speed=grip.max_descent_speed * scale,
            )
        else:
            grip = replace(grip, settle_time=grip.settle_time * scale)
    except InvalidInputError as exc:
        raise InvalidInputError(f"{factor.value} x{scale:g} is not a valid world: {exc}") from None
    return PhysicsParams(rope, grip)


def _largest_valid_radius_scale(params: PhysicsParams) -> float:
    """The largest radius scale a rope of these links takes (diameter = link length)."""
    return params.rope.link_length / (2 * params.rope.radius)


_NAME = re.compile(r"(?P<factor>[a-z_]+?)(?P<sign>[+-])(?P<pct>\d+(\.\d+)?)")
_COMBINED = re.compile(r"combined(?P<pct>\d+(\.\d+)?)")


@dataclass(frozen=True)
class PhysicsSetting:
    """How a world's (or an agent model's) physics is made from the nominal world, by name."""

    name: str  # "nominal", "mass+25", "combined25", or "file:<path>"
    factor: MismatchFactor | None = None  # the one factor scaled (None: nominal, combined, file)
    scale: float = 1.0  # its scale
    combined_level: float = 0.0  # combined: every factor drawn from U(1 - level, 1 + level)
    seed: int = 0  # combined: the setting's seed (with the task id, the per-task draw's)
    fixed: PhysicsParams | None = None  # file: the parameters read
    # An agent's model only: it also measures the rope's radius from the camera's first cloud
    # (`measured_model`), as every model measures the length ("measured": nominal otherwise).
    measures_radius: bool = False

    @property
    def is_nominal(self) -> bool:
        """The nominal world, exactly (every task)."""
        return self.name == "nominal"

    @property
    def per_task(self) -> bool:
        """Whether each task gets its own draw (the combined setting)."""
        return self.combined_level > 0

    def params_for(self, task_id: str) -> PhysicsParams:
        """The physics of task ``task_id`` under this setting."""
        if self.fixed is not None:
            return self.fixed
        if self.factor is not None:
            return scale_factor(NOMINAL, self.factor, self.scale)
        if not self.per_task:
            return NOMINAL
        return combined_params(self.combined_level, text_seed(self.seed, task_id))

    def scales_for(self, task_id: str) -> dict[str, float]:
        """Each factor's scale for task ``task_id`` (1.0 where nominal; {} for a file)."""
        if self.fixed is not None:
            return {}
        if self.factor is not None:
            return {self.factor.value: self.scale}
        if not self.per_task:
            return {}
        return combined_scales(self.combined_level, text_seed(self.seed, task_id))

    def record(self) -> dict:
        """What a results file records of this setting."""
        out: dict = {"name": self.name}
        if self.factor is not None:
            out.update(factor=self.factor.value, scale=self.scale)
        if self.per_task:
            out.update(combined_level=self.combined_level, seed=self.seed)
        if self.fixed is not None:
            out["params"] = self.fixed.to_dict()
        elif not self.per_task:
            out["params"] = self.params_for("").to_dict()
        return out


def combined_scales(level: float, seed: int) -> dict[str, float]:
    """Every factor's scale drawn from U(1 - level, 1 + level) with ``seed`` (factor order of
    `MismatchFactor`), the radius's capped where a thicker rope would not fit its (scaled) links:
    a capsule's diameter cannot exceed its length."""
    rng = np.random.default_rng(seed)
    draws = rng.uniform(1.0 - level, 1.0 + level, size=len(MismatchFactor))
    scales = {f.value: float(s) for f, s in zip(MismatchFactor, draws, strict=True)}
    cap = _largest_valid_radius_scale(NOMINAL) * scales[MismatchFactor.LENGTH.value] * (1 - 1e-9)
    scales[MismatchFactor.RADIUS.value] = min(scales[MismatchFactor.RADIUS.value], cap)
    return scales


def combined_params(level: float, seed: int) -> PhysicsParams:
    """The nominal world with every factor scaled by `combined_scales`."""
    return perturb_params(NOMINAL, level, seed)


def perturb_params(base: PhysicsParams, level: float, seed: int) -> PhysicsParams:
    """``base`` with every factor scaled by `combined_scales` (the radius capped to fit)."""
    scales = combined_scales(level, seed)
    cap = _largest_valid_radius_scale(base) * scales[MismatchFactor.LENGTH.value] * (1 - 1e-9)
    scales[MismatchFactor.RADIUS.value] = min(scales[MismatchFactor.RADIUS.value], cap)
    # Each step is checked as a rope: a radius too thick for the nominal links needs the longer
    # links first; otherwise the radius goes first (a shorter rope may need it thinner first).
    thick = scales[MismatchFactor.RADIUS.value] > _largest_valid_radius_scale(base)
    first = MismatchFactor.LENGTH if thick else MismatchFactor.RADIUS
    order = sorted(scales, key=lambda name: name != first.value)
    params = base
    for name in order:
        params = scale_factor(params, MismatchFactor(name), scales[name])
    return params


def parse_setting(text: str, *, seed: int = 0) -> PhysicsSetting:
    """The setting named ``text`` (nominal, FACTOR+PCT, FACTOR-PCT, combinedPCT) or a JSON file
    path; a one-line error naming the choices otherwise."""
    name = text.strip()
    if name == "nominal":
        return PhysicsSetting("nominal")
    if name == "measured":
        return PhysicsSetting("measured", measures_radius=True)
    match = _COMBINED.fullmatch(name)
    if match:
        level = float(match["pct"]) / 100
        if not 0 < level < 1:
            raise InvalidInputError(f"{name}: the combined level must be between 0 and 100 %")
        return PhysicsSetting(name, combined_level=level, seed=seed)
    match = _NAME.fullmatch(name)
    if match and match["factor"] in {f.value for f in MismatchFactor}:
        factor = MismatchFactor(match["factor"])
        pct = float(match["pct"]) / 100
        scale = 1.0 + pct if match["sign"] == "+" else 1.0 - pct
        scale_factor(NOMINAL, factor, scale)  # refuse an impossible world now, not per task
        return PhysicsSetting(name, factor=factor, scale=scale)
    path = Path(name)
    if path.suffix or "/" in name:  # a path, not a name
        if not path.is_file():
            raise InvalidInputError(f"physics file {path} does not exist")
        if path.suffix != ".json":
            raise InvalidInputError(f"physics file {path}: expected a .json file")
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, json.JSONDecodeError) as exc:
            raise InvalidInputError(f"{path}: not readable JSON ({exc})") from None
        return PhysicsSetting(f"file:{path}", fixed=PhysicsParams.from_dict(data, str(path)))
    factors = ", ".join(f.value for f in MismatchFactor)
    raise InvalidInputError(
        f"unknown physics setting {text!r}; expected nominal, measured (a model: nominal, "
        "measuring the rope's radius), FACTOR+PCT or FACTOR-PCT "
        f"(e.g. mass+25; factors: {factors}), combinedPCT (e.g. combined25) or a .json file"
    )


def family_settings(factor: MismatchFactor, levels: tuple[float, ...]) -> list[str]:
    """The setting names of one factor at +-each level (in percent), skipping impossible worlds."""
    names = []
    for pct in levels:
        for sign in "+-":
            name = f"{factor.value}{sign}{pct:g}"
            try:
                parse_setting(name)
            except InvalidInputError:
                continue  # e.g. radius+50: the rope would not fit its links
            names.append(name)
    return names


NOMINAL_SETTING = PhysicsSetting("nominal")

# A rope at rest measures about 0.2 % short of its links' total (the joints' slack); beyond this
# the rope in front of the robot is another rope, and the model takes the measured length.
MEASURED_LENGTH_TOLERANCE = 0.01


# Heights above the table are what a camera measures a rope's thickness by; within this the
# rope is the model's own (the matched world measures its radius exactly).
MEASURED_RADIUS_TOLERANCE = 0.02


def at_rest(nodes_k3: np.ndarray, radius: float) -> np.ndarray:
    """The chain lying on the table as a rope of ``radius`` does: every node at that height."""
    nodes = np.array(nodes_k3, dtype=float)
    nodes[:, 2] = radius
    return nodes


def measured_radius(seen_n3: np.ndarray, nodes_k3: np.ndarray, own_radius: float) -> float:
    """The radius of the rope at rest in the upper-surface cloud ``seen_n3``, lying along
    ``nodes_k3`` (its centreline in the table's plane).

    A point at distance d (in the plane) from the centreline of a rope of radius r lying on the
    table is at height r + sqrt(r^2 - d^2); the radius is the one that fits every point's height
    best (a robust least-squares fit, from ``own_radius``; points more than two of the model's
    diameters high, on a crossing strand, are left out)."""
    from scipy.optimize import least_squares
    from scipy.spatial import cKDTree

    seen = np.asarray(seen_n3, dtype=float)
    if seen.ndim != 2 or seen.shape[1] != 3 or len(seen) == 0:
        raise InvalidInputError(f"a rope's cloud must be (n > 0, 3), got {seen.shape}")
    nodes = np.asarray(nodes_k3, dtype=float)[:, :2]
    t = np.linspace(0.0, 1.0, 20, endpoint=False)
    line = (nodes[:-1, None, :] + t[None, :, None] * (nodes[1:] - nodes[:-1])[:, None, :]).reshape(
        -1, 2
    )
    line = np.vstack([line, nodes[-1:]])
    d_n = cKDTree(line).query(seen[:, :2])[0]
    z_n = seen[:, 2]
    keep = z_n < 4.0 * own_radius
    d_n, z_n = d_n[keep], z_n[keep]
    if len(z_n) == 0:
        raise InvalidInputError("no point of the cloud lies on a rope resting on the table")

    def residual(r: np.ndarray) -> np.ndarray:
        return z_n - r[0] - np.sqrt(np.maximum(r[0] ** 2 - d_n**2, 0.0))

    fit = least_squares(
        residual,
        x0=[own_radius],
        bounds=([0.1 * own_radius], [10.0 * own_radius]),
        loss="soft_l1",
        f_scale=0.1 * own_radius,
    )
    return float(fit.x[0])


def measured_model(
    model: PhysicsParams, start_nodes_k3: np.ndarray, seen_n3: np.ndarray | None = None
) -> PhysicsParams:
    """The agent's model with the rope length (and, given the camera's cloud ``seen_n3`` of the
    start rope at rest, the radius) it measures at the start of an episode.

    A robot sees how long its rope is, so a model never simulates a rope of another length
    than the one in front of it (its transferred grasps would land off the model's rope): where
    the start rope's length differs from the model's by more than 1 %, the model takes it (its
    radius capped so that the rope still fits its links). With ``seen_n3`` the same for the
    radius, measured from the cloud's heights (`measured_radius`), beyond 2 %. Every other
    factor stays the model's.
    """
    from knotlab.core.world.rope import rope_length

    rope = model.rope
    length, radius = rope.length, rope.radius
    measured = rope_length(start_nodes_k3)
    if abs(measured - length) > MEASURED_LENGTH_TOLERANCE * length:
        length = measured
    if seen_n3 is not None:
        seen_radius = measured_radius(seen_n3, start_nodes_k3, radius)
        if abs(seen_radius - radius) > MEASURED_RADIUS_TOLERANCE * radius:
            radius = seen_radius
    if (length, radius) == (rope.length, rope.radius):
        return model
    radius = min(radius, 0.5 * length / rope.n_links * (1 - 1e-9))  # the rope fits its links
    return PhysicsParams(replace(rope, length=length, radius=radius), model.gripper)

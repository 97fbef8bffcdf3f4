"""Physics settings: names, files, the combined draw, what each factor scales, measured length."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from knotlab.core.errors import InvalidInputError
from knotlab.core.world.mismatch import (
    NOMINAL,
    MismatchFactor,
    PhysicsParams,
    at_rest,
    combined_params,
    family_settings,
    measured_model,
    measured_radius,
    parse_setting,
    scale_factor,
)
from knotlab.core.world.rope import straight_rope


def test_nominal_is_the_default_world_exactly():
    setting = parse_setting("nominal")
    assert setting.is_nominal and not setting.per_task
    assert setting.params_for("any-task") == PhysicsParams() == NOMINAL
    assert setting.params_for("x").rope.table_friction is None  # the table's friction = rope's


@pytest.mark.parametrize(
    ("name", "path", "value"),
    [
        ("mass+25", ("rope", "mass"), 0.25),
        ("mass-50", ("rope", "mass"), 0.1),
        ("radius-10", ("rope", "radius"), 0.009),
        ("length+10", ("rope", "length"), 1.1),
        ("grasp_reach+50", ("gripper", "grasp_radius"), 0.045),
        ("grip_force-25", ("gripper", "grip_force"), 22.5),
        ("settle_time+10", ("gripper", "settle_time"), 1.1),
        ("gripper_speed-50", ("gripper", "max_descent_speed"), 0.125),
        ("damping+25", ("rope", "angular_damping"), 0.625),
        ("table_friction-25", ("rope", "table_friction"), 0.6),
    ],
)
def test_one_factor_settings_scale_exactly_that_factor(name, path, value):
    params = parse_setting(name).params_for("t")
    assert getattr(getattr(params, path[0]), path[1]) == pytest.approx(value)
    changed = {
        (section, f)
        for section in ("rope", "gripper")
        for f, v in vars(getattr(params, section)).items()
        if v != getattr(getattr(NOMINAL, section), f)
    }
    assert path in changed
    assert len(changed) <= 2  # damping and speed scale two fields, friction two coefficients


def test_rope_friction_changes_rope_on_rope_and_leaves_rope_on_table_alone():
    # PyBullet multiplies the two bodies' coefficients (checked in test_sim).
    for scale in (0.5, 0.75, 1.5):
        rope = scale_factor(NOMINAL, MismatchFactor.ROPE_FRICTION, scale).rope
        assert rope.table_friction is not None
        assert rope.friction * rope.table_friction == pytest.approx(NOMINAL.rope.friction**2)
        assert rope.friction**2 == pytest.approx(scale * NOMINAL.rope.friction**2)
        table = scale_factor(NOMINAL, MismatchFactor.TABLE_FRICTION, scale).rope
        assert table.friction == NOMINAL.rope.friction
        assert table.table_friction == pytest.approx(scale * NOMINAL.rope.friction)


def test_a_rope_too_thick_for_its_links_is_refused_in_one_line_and_left_out_of_families():
    with pytest.raises(InvalidInputError, match=r"radius\+50.*not a valid world|radius x1.5"):
        parse_setting("radius+50")
    assert family_settings(MismatchFactor.RADIUS, (10, 50)) == [
        "radius+10",
        "radius-10",
        "radius-50",
    ]


@pytest.mark.parametrize("bad", ["massy+5", "mass*2", "combined0", "combined100", "", "mass+"])
def test_unknown_or_impossible_names_get_one_line_naming_the_forms(bad):
    with pytest.raises(InvalidInputError) as err:
        parse_setting(bad)
    assert "\n" not in str(err.value)


def test_combined_draws_are_per_task_seeded_and_always_a_valid_rope():
    a = parse_setting("combined25", seed=3)
    assert a.params_for("main-test-0001") == a.params_for("main-test-0001")
    assert a.params_for("main-test-0001") != a.params_for("main-test-0002")
    assert parse_setting("combined25", seed=4).params_for("main-test-0001") != a.params_for(
        "main-test-0001"
    )
    scales = a.scales_for("main-test-0001")
    assert set(scales) == {f.value for f in MismatchFactor}
    assert all(0.75 <= s <= 1.25 for s in scales.values())
    for seed in range(300):  # every draw at +-50 % is a rope that fits its links
        rope = combined_params(0.5, seed).rope
        assert 2 * rope.radius <= rope.link_length
    record = a.record()
    assert record["combined_level"] == 0.25 and record["seed"] == 3


def test_a_json_file_overrides_named_fields_and_bad_files_are_refused(tmp_path):
    good = tmp_path / "world.json"
    good.write_text(json.dumps({"rope": {"mass": 0.3}, "gripper": {"grip_force": 10.0}}))
    params = parse_setting(str(good)).params_for("t")
    assert params.rope.mass == 0.3 and params.gripper.grip_force == 10.0
    assert params.rope.radius == NOMINAL.rope.radius
    for text, message in [
        ({"rope": {"colour": 1}}, "no field 'colour'"),
        ({"table": {}}, "unknown section 'table'"),
        ({"rope": {"mass": -1}}, "mass must be positive"),
    ]:
        bad = tmp_path / "bad.json"
        bad.write_text(json.dumps(text))
        with pytest.raises(InvalidInputError, match=message):
            parse_setting(str(bad))
    with pytest.raises(InvalidInputError, match="does not exist"):
        parse_setting(str(tmp_path / "missing.json"))


def test_the_model_measures_a_rope_of_another_length_and_keeps_its_own_otherwise():
    nominal_rope = straight_rope(41, 0.998)  # a rope at rest measures a little short
    assert measured_model(NOMINAL, nominal_rope) is NOMINAL
    longer = measured_model(NOMINAL, straight_rope(41, 1.3))
    assert longer.rope.length == pytest.approx(1.3)
    assert longer.rope.mass == NOMINAL.rope.mass and longer.gripper == NOMINAL.gripper
    short = measured_model(NOMINAL, straight_rope(41, 0.6))
    assert 2 * short.rope.radius <= short.rope.link_length  # thinned to fit its shorter links
    assert math.isclose(short.rope.length, 0.6)
    assert np.isfinite(short.rope.radius)


def test_a_measuring_model_takes_the_radius_the_camera_sees_and_keeps_its_own_otherwise():
    from knotlab.core.world.observation import surface_cloud_of_nodes

    rope = straight_rope(41, 0.998)
    rope[:, 1] = 0.01 * np.sin(np.linspace(0.0, 6.0, 41))  # bent a little, as starts are

    def seen(radius: float) -> np.ndarray:  # the camera's cloud of the world's rope at rest
        return surface_cloud_of_nodes(at_rest(rope, radius), radius)

    for radius in (0.006, 0.0075, 0.01, 0.0125):
        got = measured_radius(seen(radius), rope, NOMINAL.rope.radius)
        assert got == pytest.approx(radius, rel=3e-3)  # within 0.3 %
    assert measured_model(NOMINAL, rope, seen(NOMINAL.rope.radius)) is NOMINAL  # matched
    assert measured_model(NOMINAL, rope, seen(1.01 * NOMINAL.rope.radius)) is NOMINAL  # within 2 %
    thick = measured_model(NOMINAL, rope, seen(0.0125))  # as thick as its links allow
    assert thick.rope.radius == pytest.approx(0.0125, rel=3e-3) and thick.rope.radius <= 0.0125
    assert thick.rope.length == NOMINAL.rope.length and thick.gripper == NOMINAL.gripper
    assert measured_model(NOMINAL, rope) is NOMINAL  # no cloud: the radius is not measured
    with pytest.raises(InvalidInputError, match="cloud"):
        measured_radius(np.zeros((0, 3)), rope, 0.01)
    setting = parse_setting("measured")
    assert setting.measures_radius and setting.params_for("t") == NOMINAL
    assert not parse_setting("nominal").measures_radius

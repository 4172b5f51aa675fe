"""Printer profiles: embedded default, TOML round trip, validation errors, firmware import."""

import numpy as np
import pytest

from ffcomp.errors import ProfileError
from ffcomp.profile import default_profile, load_profile, profile_to_toml, save_profile
from ffcomp.profile_import import from_klipper_cfg, from_m665


def test_default_is_table_one(profile):
    d = profile.dynamics
    assert d.m == (0.177,) * 3 and d.k == (9.44e4,) * 3 and d.b_nt == 27.9
    assert d.m_nt == pytest.approx(0.156 + 1.5 * 0.032)
    assert np.sqrt(d.k[0] / d.m[0]) == pytest.approx(730, rel=1e-3)  # Table I w_n
    assert profile.geometry.tower_angles_deg == (0.0, 120.0, 240.0)  # the paper's frame


def test_toml_round_trip(tmp_path, profile):
    path = tmp_path / "p.toml"
    save_profile(profile, path)
    again = load_profile(path)
    assert again.geometry == profile.geometry
    assert again.limits == profile.limits
    assert again.dynamics == profile.dynamics


def _write(tmp_path, text):
    p = tmp_path / "bad.toml"
    p.write_text(text)
    return p


BASE = profile_to_toml(default_profile())


@pytest.mark.parametrize(
    "old,new,key,value",
    [
        ("m = 0.177", "m = -0.177", "dynamics.m", "-0.177"),
        ("k = 94400.0", "k = \"stiff\"", "dynamics.k", "stiff"),
        ("arm_length_mm = 330.0", "arm_length_mm = 250.0", "geometry.arm_length_mm[0]", "250.0"),
        ("planner = \"klipper\"", "planner = \"grbl\"", "limits.planner", "grbl"),
        ("z_max_mm = 300.0", "z_max_mm = -1.0", "geometry.z_max_mm", "-1.0"),
        ("print_radius_mm = 135.0", "print_radius_mm = 175.0", "geometry.arm_length_mm[0]", "330.0"),
        ("max_accel_mm_s2 = 10000.0", "max_accel_mm_s2 = 0.0", "limits.max_accel_mm_s2", "0.0"),
        ("b_nt = 27.9", "b_nt = 27.9\nbogus = 1", "dynamics.bogus", "1"),
        ("m = 0.177", "m = [0.1, 0.2]", "dynamics.m", "[0.1, 0.2]"),
        ("min_arm_angle_deg = 15.0", "min_arm_angle_deg = 40.0", "geometry.print_radius_mm", "135.0"),
    ],
)
def test_malformed_profiles_name_key_and_value(tmp_path, old, new, key, value):
    assert old in BASE
    p = _write(tmp_path, BASE.replace(old, new, 1))
    with pytest.raises(ProfileError) as e:
        load_profile(p)
    msg = str(e.value)
    assert f"'{key}'" in msg and value in msg and str(p) in msg


def test_not_toml_and_missing_file(tmp_path):
    with pytest.raises(ProfileError, match="not valid TOML"):
        load_profile(_write(tmp_path, "[geometry\narm = 1"))
    with pytest.raises(ProfileError, match="cannot read"):
        load_profile(tmp_path / "nope.toml")


def test_per_tower_values(tmp_path):
    p = _write(tmp_path, BASE.replace("k = 94400.0", "k = [94400.0, 90000.0, 95000.0]"))
    prof = load_profile(p)
    assert prof.dynamics.k == (94400.0, 90000.0, 95000.0)
    assert "90000.0" in profile_to_toml(prof)


KLIPPER = """
[printer]
kinematics: delta
max_velocity: 300
max_accel: 3000
max_z_velocity: 150
delta_radius: 174.75
print_radius: 140   # a comment
minimum_z_position: -5

[stepper_a]
rotation_distance: 40
microsteps: 32
position_endstop: 297.05
arm_length: 333.0

[stepper_b]
position_endstop: 297.0

[stepper_c]
angle: 91
position_endstop: 298.0

#*# <---------------------- SAVE_CONFIG ---------------------->
#*# [printer]
#*# delta_radius = 175.5
"""


def test_klipper_import(tmp_path):
    p = tmp_path / "printer.cfg"
    p.write_text(KLIPPER)
    prof = from_klipper_cfg(p)
    g, lim = prof.geometry, prof.limits
    assert g.delta_radius_mm == (175.5,) * 3  # SAVE_CONFIG wins
    assert g.arm_length_mm == (333.0,) * 3
    assert g.tower_angles_deg == (210.0, 330.0, 91.0)  # Klipper frame kept, C angle overridden
    assert g.print_radius_mm == 140 and g.z_min_mm == -5 and g.z_max_mm == 297.0
    assert lim.max_z_velocity_mm_s == 150 and lim.max_z_accel_mm_s2 == 3000
    assert lim.steps_per_mm == pytest.approx(200 * 32 / 40)


def test_klipper_import_errors(tmp_path):
    p = tmp_path / "printer.cfg"
    p.write_text(KLIPPER.replace("kinematics: delta", "kinematics: corexy"))
    with pytest.raises(ProfileError, match="kinematics"):
        from_klipper_cfg(p)
    p.write_text(KLIPPER.replace("max_accel: 3000", "max_accel: fast"))
    with pytest.raises(ProfileError, match="max_accel.*fast"):
        from_klipper_cfg(p)


def test_m665_import():
    prof = from_m665("M665 L250:251:249 R130 B85 H240 X0.5 ; comment")
    g = prof.geometry
    assert g.arm_length_mm == (250.0, 251.0, 249.0)
    assert g.delta_radius_mm == (130.0,) * 3
    assert g.tower_angles_deg == (210.5, 330.0, 90.0)
    assert g.print_radius_mm == 85 and g.z_max_mm == 240
    assert prof.limits.planner == "marlin"
    # the positions the firmware computes: tower A at 210 degrees
    q = prof.geometry_si().tower_xy_m[0]
    assert np.degrees(np.arctan2(q[1], q[0])) % 360 == pytest.approx(210.5)


def test_m665_unreachable_geometry_is_an_error():
    with pytest.raises(ProfileError, match="unreachable workspace"):
        from_m665("M665 L250 R160 B85")
    with pytest.raises(ProfileError, match="M665 R"):
        from_m665("M665 L250 Rabc")

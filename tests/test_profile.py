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


def test_klipper_import_reads_the_arc_resolution(tmp_path):
    """``[gcode_arcs] resolution`` is the chord length Klipper splits G2/G3 into; without the section
    (Klipper then refuses arcs) the profile carries Klipper's default, not the base profile's value."""
    from dataclasses import replace

    from ffcomp.profile import default_profile

    p = tmp_path / "printer.cfg"
    p.write_text(KLIPPER.replace("[stepper_a]", "[gcode_arcs]\nresolution: 0.1\n\n[stepper_a]"))
    assert from_klipper_cfg(p).limits.arc_resolution_mm == 0.1
    p.write_text(KLIPPER)
    base = default_profile()
    base = replace(base, limits=replace(base.limits, arc_resolution_mm=0.25))
    assert from_klipper_cfg(p, base).limits.arc_resolution_mm == 1.0
    p.write_text(KLIPPER.replace("[stepper_a]", "[gcode_arcs]\nresolution: fine\n\n[stepper_a]"))
    with pytest.raises(ProfileError, match="resolution.*fine"):
        from_klipper_cfg(p)


def test_arc_resolution_is_checked(tmp_path):
    from ffcomp.profile import default_profile, save_profile

    path = tmp_path / "p.toml"
    save_profile(default_profile(), path)
    text = path.read_text()
    assert "arc_resolution_mm = 1.0" in text
    path.write_text(text.replace("arc_resolution_mm = 1.0", "arc_resolution_mm = 0.001"))
    with pytest.raises(ProfileError, match="arc_resolution_mm"):
        load_profile(path)
    path.write_text(text.replace("arc_resolution_mm = 1.0", "arc_resolution_mm = 0.2"))
    assert load_profile(path).limits.arc_resolution_mm == 0.2


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


# ------------------------------------------------------------------ required keys, version, file type

@pytest.mark.parametrize("drop", ["k = 94400.0\n", "arm_length_mm = 330.0\n", "max_accel_mm_s2 = 10000.0\n",
                                  "planner = \"klipper\"\n"])
def test_required_key_missing_is_an_error(tmp_path, drop):
    assert drop in BASE
    p = _write(tmp_path, BASE.replace(drop, "", 1))
    key = drop.split(" =")[0]
    with pytest.raises(ProfileError, match=f"{key}' = None: required key missing"):
        load_profile(p)


def test_empty_profile_and_missing_section(tmp_path):
    with pytest.raises(ProfileError, match=r"section \[geometry\] missing"):
        load_profile(_write(tmp_path, ""))
    start = BASE.index("[dynamics]")
    with pytest.raises(ProfileError, match=r"section \[dynamics\] missing"):
        load_profile(_write(tmp_path, BASE[:start]))


@pytest.mark.parametrize("version", ["99", "0", "\"1\"", "true"])
def test_unknown_profile_version_is_an_error(tmp_path, version):
    assert BASE.startswith("ffcomp_profile = 1\n")
    p = _write(tmp_path, BASE.replace("ffcomp_profile = 1", f"ffcomp_profile = {version}", 1))
    with pytest.raises(ProfileError, match="ffcomp_profile.*unsupported profile format version"):
        load_profile(p)


def test_z_limits_default_to_the_xy_limits_as_in_klipper(tmp_path):
    text = BASE.replace("max_z_velocity_mm_s = 300.0\n", "").replace("max_z_accel_mm_s2 = 10000.0\n", "")
    text = text.replace("max_accel_mm_s2 = 10000.0", "max_accel_mm_s2 = 2500.0")
    lim = load_profile(_write(tmp_path, text)).limits
    assert lim.max_z_accel_mm_s2 == 2500.0 and lim.max_z_velocity_mm_s == lim.max_velocity_mm_s


def test_binary_profile_is_a_clean_error(tmp_path, capsys):
    from cli_util import run

    p = tmp_path / "p.toml"
    p.write_bytes(b"\x00\xff\xfe\x89PNG binary")
    with pytest.raises(ProfileError, match="not a text .*byte 0xff at offset 1"):
        load_profile(p)
    code, _, err = run(capsys, "model", "show", "--profile", p)
    assert code == 2 and "Traceback" not in err and "not a text" in err
    cfg = tmp_path / "printer.cfg"
    cfg.write_bytes(b"\xff\xfe[printer]")
    with pytest.raises(ProfileError, match="not a text file"):
        from_klipper_cfg(cfg)


# ------------------------------------------------------------------ Klipper's print radius rule

# The values that matter of Klipper's own config/example-delta.cfg and
# config/printer-monoprice-mini-delta-2017.cfg (transcribed; no print_radius in either).
KLIPPER_EXAMPLE_DELTA = """
[stepper_a]
microsteps: 16
rotation_distance: 40
position_endstop: 297.05
arm_length: 333.0
[stepper_b]
microsteps: 16
rotation_distance: 40
[stepper_c]
microsteps: 16
rotation_distance: 40
[printer]
kinematics: delta
max_velocity: 300
max_accel: 3000
max_z_velocity: 150
delta_radius: 174.75
"""

KLIPPER_MINI_DELTA = """
[stepper_a]
microsteps: 16
rotation_distance: 56
position_endstop: 125.00
arm_length: 120.8
[stepper_b]
microsteps: 16
rotation_distance: 56
[stepper_c]
microsteps: 16
rotation_distance: 56
[printer]
kinematics: delta
max_velocity: 150
max_accel: 1200
max_z_velocity: 100
minimum_z_position: -10.0
delta_radius: 63.00
"""


@pytest.mark.parametrize("text,arm,radius,step_mm", [(KLIPPER_EXAMPLE_DELTA, 333.0, 174.75, 40 / 3200),
                                                     (KLIPPER_MINI_DELTA, 120.8, 63.0, 56 / 3200)],
                         ids=["example-delta", "monoprice-mini-delta"])
def test_klipper_configs_import_with_the_radius_klipper_allows(tmp_path, capsys, text, arm, radius, step_mm):
    """Klipper caps the build radius where a tower would move 12x as fast as the nozzle (4 x
    SLOW_RATIO); checked here from the geometry itself: at the imported radius, with the nozzle
    opposite a tower, the tower's speed over the nozzle's speed is 12 (up to the half-step term)."""
    from cli_util import run

    cfg = tmp_path / "printer.cfg"
    cfg.write_text(text)
    notes: list = []
    prof = from_klipper_cfg(cfg, notes=notes)
    r = prof.geometry.print_radius_mm
    assert r < radius and r < arm - radius  # capped, not the configured default (= delta_radius)
    d = radius + r  # horizontal reach of the arm of the tower opposite the nozzle
    ratio = d / np.sqrt(arm ** 2 - d ** 2)  # dq/dx of that tower (IK: q = z + sqrt(L^2 - d^2))
    # Klipper's formula carries a half-step term h: the ratio is 12 at h = 0, and h moves the radius by
    # at most h, so the ratio by at most h d(ratio)/dd = h L^2 / (L^2 - d^2)^1.5
    assert ratio >= 12.0 and ratio - 12.0 <= 1.1 * (step_mm / 2) * arm ** 2 / (arm ** 2 - d ** 2) ** 1.5
    # the same ratio from ffcomp's own Jacobian at that pose
    geo = prof.geometry_si()
    ang = np.radians(prof.geometry.tower_angles_deg[0])
    x = -r * 1e-3 * np.array([np.cos(ang), np.sin(ang), 0.0]) + np.array([0, 0, 0.05])
    from ffcomp.kinematics import inverse

    h = 1e-7
    u = np.array([np.cos(ang), np.sin(ang), 0.0])
    dq = (inverse(geo, (x + h * u)[None])[0, 0] - inverse(geo, (x - h * u)[None])[0, 0]) / (2 * h)
    assert abs(dq) == pytest.approx(ratio, rel=1e-5)
    assert notes and "capped as Klipper does" in notes[0]
    assert prof.geometry.min_arm_angle_deg < 5.0  # the arm angle Klipper accepts there
    code, _, err = run(capsys, "profile", "import", "--klipper", cfg, "-o", tmp_path / "p.toml")
    assert code == 0 and "capped" in err, err
    assert load_profile(tmp_path / "p.toml").geometry.print_radius_mm == pytest.approx(r)


def test_klipper_print_radius_kept_when_reachable(tmp_path):
    cfg = tmp_path / "printer.cfg"
    cfg.write_text(KLIPPER_EXAMPLE_DELTA.replace("delta_radius: 174.75", "delta_radius: 174.75\nprint_radius: 120"))
    notes: list = []
    prof = from_klipper_cfg(cfg, notes=notes)
    assert prof.geometry.print_radius_mm == 120 and not notes
    assert prof.geometry.min_arm_angle_deg == default_profile().geometry.min_arm_angle_deg


# ------------------------------------------------------------------ M665 words

def test_m665_bad_value_is_not_a_number_not_missing():
    with pytest.raises(ProfileError, match="'M665 L' = 'abc': not a number"):
        from_m665("M665 L abc R130 B85")
    with pytest.raises(ProfileError, match="'M665 R' = 'nan': not a finite number"):
        from_m665("M665 L250 Rnan B85")
    prof = from_m665("M665 L250R130B85")  # words without spaces
    assert prof.geometry.arm_length_mm == (250.0,) * 3 and prof.geometry.print_radius_mm == 85


def test_m665_without_b_needs_a_print_radius():
    with pytest.raises(ProfileError, match="'M665 B'.*missing.*--print-radius"):
        from_m665("M665 L250 R130 H240")
    prof = from_m665("M665 L250 R130 H240", print_radius_mm=80.0)
    assert prof.geometry.print_radius_mm == 80.0

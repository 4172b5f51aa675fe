#!/usr/bin/env python3
"""Regenerate ffcomp's sample G-code: STL models, real slicer runs, hand-written and
synthetic stress files.

Printer for every sample: a delta with a circular bed of radius 135 mm centred at (0, 0),
300 mm tall, 0.4 mm nozzle, 1.75 mm filament.

    python samples/make_samples.py                 # models + small samples -> samples/
    python samples/make_samples.py --large         # also the big plate -> samples/large/
    python samples/make_samples.py --large-only    # only the big plate (for the benchmark)
    python samples/make_samples.py --outdir /tmp/s # write somewhere else

Slicers (Debian bookworm packages): ``prusa-slicer`` (2.5.0) and ``cura-engine`` (4.13.0)
with ``fdmprinter.def.json`` from the ``cura`` package. A slicer that is absent is skipped
with a message; everything else is still produced. Needs only numpy.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent

# ---------------------------------------------------------------------------------------
# Printer (all samples)
# ---------------------------------------------------------------------------------------
BED_RADIUS_MM = 135.0
PRINT_HEIGHT_MM = 300.0
NOZZLE_MM = 0.4
FILAMENT_MM = 1.75
FILAMENT_AREA_MM2 = math.pi * (FILAMENT_MM / 2.0) ** 2
BED_POLYGON_SIDES = 64


def bed_shape_arg(radius_mm: float = BED_RADIUS_MM, sides: int = BED_POLYGON_SIDES) -> str:
    """PrusaSlicer --bed-shape value: a regular polygon centred at (0, 0), 'XxY,XxY,...'."""
    pts = []
    for k in range(sides):
        a = 2.0 * math.pi * k / sides
        pts.append(f"{radius_mm * math.cos(a):.3f}x{radius_mm * math.sin(a):.3f}")
    return ",".join(pts)


# ---------------------------------------------------------------------------------------
# STL models
# ---------------------------------------------------------------------------------------
def write_stl(path: Path, tris: np.ndarray, name: str) -> None:
    """Write triangles (N, 3, 3) in mm as binary STL, normals from the winding (CCW = out)."""
    tris = np.asarray(tris, dtype=np.float64)
    n = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.divide(n, norm, out=np.zeros_like(n), where=norm > 0)
    rec = np.zeros(len(tris), dtype=[("n", "<f4", 3), ("v", "<f4", (3, 3)), ("attr", "<u2")])
    rec["n"] = n
    rec["v"] = tris
    header = f"ffcomp sample model: {name}".encode("ascii")[:80].ljust(80, b" ")
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as f:
        f.write(header)
        f.write(np.uint32(len(tris)).tobytes())
        f.write(rec.tobytes())


def _fan(poly: np.ndarray, z: float, up: bool) -> list:
    """Triangulate a convex CCW polygon (M, 2) at height z; normal +z if up else -z."""
    tris = []
    p0 = (*poly[0], z)
    for i in range(1, len(poly) - 1):
        a = (*poly[i], z)
        b = (*poly[i + 1], z)
        tris.append((p0, a, b) if up else (p0, b, a))
    return tris


def _walls(poly: np.ndarray, z0: float, z1: float, outward: bool) -> list:
    """Side walls of a CCW polygon; outward=True for an outer boundary, False for a hole."""
    tris = []
    m = len(poly)
    for i in range(m):
        a, b = poly[i], poly[(i + 1) % m]
        a0, b0, a1, b1 = (*a, z0), (*b, z0), (*a, z1), (*b, z1)
        if outward:
            tris += [(a0, b0, b1), (a0, b1, a1)]
        else:
            tris += [(a0, b1, b0), (a0, a1, b1)]
    return tris


def convex_prism(poly: np.ndarray, z0: float, z1: float) -> list:
    """Closed prism over a convex CCW polygon."""
    return _fan(poly, z0, up=False) + _fan(poly, z1, up=True) + _walls(poly, z0, z1, True)


def ring_prism(outer: np.ndarray, inner: np.ndarray, z0: float, z1: float) -> list:
    """Closed prism over the region between two CCW polygons with matching vertices."""
    tris = _walls(outer, z0, z1, True) + _walls(inner, z0, z1, False)
    m = len(outer)
    for i in range(m):
        j = (i + 1) % m
        for z, up in ((z1, True), (z0, False)):
            oi, oj, ii, ij = (*outer[i], z), (*outer[j], z), (*inner[i], z), (*inner[j], z)
            if up:
                tris += [(oi, oj, ij), (oi, ij, ii)]
            else:
                tris += [(oi, ij, oj), (oi, ii, ij)]
    return tris


def inset_polygon(poly: np.ndarray, d: float) -> np.ndarray:
    """Mitred inward offset of a simple CCW polygon by d (fine for right-angle polygons)."""
    m = len(poly)
    out = np.empty_like(poly)
    for i in range(m):
        p_prev, p, p_next = poly[i - 1], poly[i], poly[(i + 1) % m]
        e1, e2 = p - p_prev, p_next - p
        n1 = np.array([-e1[1], e1[0]]) / np.linalg.norm(e1)  # left normal = inward for CCW
        n2 = np.array([-e2[1], e2[0]]) / np.linalg.norm(e2)
        out[i] = p + d * (n1 + n2) / (1.0 + float(n1 @ n2))
    return out


def rect(cx: float, cy: float, w: float, h: float) -> np.ndarray:
    return np.array(
        [
            [cx - w / 2, cy - h / 2],
            [cx + w / 2, cy - h / 2],
            [cx + w / 2, cy + h / 2],
            [cx - w / 2, cy + h / 2],
        ]
    )


def circle(cx: float, cy: float, r: float, n: int) -> np.ndarray:
    a = 2.0 * np.pi * np.arange(n) / n
    return np.stack([cx + r * np.cos(a), cy + r * np.sin(a)], axis=1)


def notched_square(
    side: float, notch_w: float, notch_d: float, notch_from_corner: float, cx: float = 0.0, cy: float = 0.0
) -> np.ndarray:
    """CCW square outline with two rectangular notches cut into each side."""
    h = side / 2.0
    pts = []
    # walk the bottom side (y = -h) from x=-h to x=+h, then rotate it for the other sides
    base = [(-h, -h)]
    for c in (-h + notch_from_corner, h - notch_from_corner - notch_w):
        base += [(c, -h), (c, -h + notch_d), (c + notch_w, -h + notch_d), (c + notch_w, -h)]
    for k in range(4):
        a = k * np.pi / 2
        ca, sa = math.cos(a), math.sin(a)
        for x, y in base:
            pts.append((cx + ca * x - sa * y, cy + sa * x + ca * y))
    return np.array(pts)


def model_cube(size: float = 20.0, cx: float = 0.0, cy: float = 0.0) -> list:
    return convex_prism(rect(cx, cy, size, size), 0.0, size)


def model_cylinder(
    diameter: float = 40.0, height: float = 30.0, cx: float = 0.0, cy: float = 0.0, segments: int = 180
) -> list:
    return convex_prism(circle(cx, cy, diameter / 2.0, segments), 0.0, height)


def model_ringing_tower(
    side: float = 60.0, height: float = 40.0, wall: float = 1.2, cx: float = 0.0, cy: float = 0.0
) -> list:
    """Hollow, open, thin-walled square tower with sharp corners and 3x1 mm notches cut
    8 mm from every corner (Klipper-ringing-tower style), wall `wall` mm thick."""
    outer = notched_square(side, notch_w=3.0, notch_d=1.0, notch_from_corner=8.0, cx=cx, cy=cy)
    inner = inset_polygon(outer, wall)
    return ring_prism(outer, inner, 0.0, height)


# The big plate: every object lies inside radius 120 mm.
def plate_objects() -> list[tuple[str, list]]:
    objs = [("plate_00_ringing_tower", model_ringing_tower(60.0, 40.0, 1.2))]
    for k in range(8):  # inner ring r = 80: cylinders and cubes alternate
        a = 2 * math.pi * k / 8 + math.pi / 8
        x, y = 80 * math.cos(a), 80 * math.sin(a)
        if k % 2 == 0:
            objs.append((f"plate_{k + 1:02d}_cylinder", model_cylinder(36.0, 30.0, x, y)))
        else:
            objs.append((f"plate_{k + 1:02d}_cube", model_cube(25.0, x, y)))
    for k in range(8):  # outer ring r = 110: small cubes (corner reach < 118 mm)
        a = 2 * math.pi * k / 8
        x, y = 110 * math.cos(a), 110 * math.sin(a)
        objs.append((f"plate_{k + 9:02d}_cube12", model_cube(12.0, x, y)))
    return objs


def make_models(models_dir: Path) -> dict[str, Path]:
    specs = {
        "cube20": ("20 mm calibration cube", model_cube(20.0)),
        "ringing_tower": ("60x60x40 mm notched thin-wall ringing tower", model_ringing_tower()),
        "ringing_tower_6mm": ("ringing tower, first 6 mm only", model_ringing_tower(height=6.0)),
        "cylinder40x30": ("cylinder d40 h30", model_cylinder(40.0, 30.0)),
    }
    out = {}
    for key, (desc, tris) in specs.items():
        p = models_dir / f"{key}.stl"
        write_stl(p, np.array(tris), desc)
        out[key] = p
    return out


def make_plate_models(plate_dir: Path) -> list[Path]:
    paths = []
    for name, tris in plate_objects():
        p = plate_dir / f"{name}.stl"
        write_stl(p, np.array(tris), name)
        paths.append(p)
    return paths


# ---------------------------------------------------------------------------------------
# G-code helpers
# ---------------------------------------------------------------------------------------
def e_per_mm(width_mm: float, height_mm: float) -> float:
    """Filament length per mm of path for a rectangular bead width x height."""
    return width_mm * height_mm / FILAMENT_AREA_MM2


def fnum(v: float, nd: int = 3) -> str:
    """Shortest fixed-point text with at most nd decimals (12000.0 -> '12000', 0.50 -> '0.5')."""
    s = f"{v:.{nd}f}"
    if "." in s:
        s = s.rstrip("0").rstrip(".")
    return "0" if s in ("-0", "") else s


def gcode_checksum(line: str) -> int:
    """Marlin/RepRap checksum: XOR of all bytes before '*'."""
    c = 0
    for b in line.encode("ascii"):
        c ^= b
    return c


def _pairs(pts: list) -> list:
    """Consecutive (a, b) pairs of a polyline."""
    return [(pts[i], pts[i + 1]) for i in range(len(pts) - 1)]


def write_text(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text if text.endswith("\n") else text + "\n")


PREAMBLE = """M140 S60 ; bed
M104 S210 ; hotend
G28 ; home all towers
M190 S60
M109 S210
G90
G21
M82 ; absolute extrusion
G92 E0
M106 S255
"""
POSTAMBLE = """G91
G1 Z5 F1200
G90
M107
M104 S0
M140 S0
G28 ; park at the top
M84
"""


class PathWriter:
    """Emit G1 moves with absolute E for a single bead size."""

    def __init__(self, width_mm: float = 0.45, height_mm: float = 0.2):
        self.k = e_per_mm(width_mm, height_mm)
        self.e = 0.0
        self.x = self.y = self.z = None
        self.lines: list[str] = []

    def travel(self, x: float, y: float, z: float | None = None, f: float = 12000) -> None:
        words = ["G0", f"X{fnum(x)}", f"Y{fnum(y)}"]
        if z is not None:
            words.append(f"Z{fnum(z)}")
            self.z = z
        words.append(f"F{fnum(f, 0)}")
        self.lines.append(" ".join(words))
        self.x, self.y = x, y

    def extrude(self, x: float, y: float, f: float | None = None) -> None:
        d = math.hypot(x - self.x, y - self.y)
        self.e += d * self.k
        words = ["G1", f"X{fnum(x)}", f"Y{fnum(y)}", f"E{fnum(self.e, 5)}"]
        if f is not None:
            words.append(f"F{fnum(f, 0)}")
        self.lines.append(" ".join(words))
        self.x, self.y = x, y

    def retract(self, mm: float = 0.8) -> None:
        self.e -= mm
        self.lines.append(f"G1 E{fnum(self.e, 5)} F2100")

    def unretract(self, mm: float = 0.8) -> None:
        self.e += mm
        self.lines.append(f"G1 E{fnum(self.e, 5)} F2100")

    def comment(self, text: str) -> None:
        self.lines.append(f";{text}")


# ---------------------------------------------------------------------------------------
# Synthetic stress files
# ---------------------------------------------------------------------------------------
def _stress_file(title: str, limits: list[str], body: PathWriter) -> str:
    head = [
        f"; ffcomp synthetic stress sample: {title}",
        "; generated by samples/make_samples.py (absolute XYZ, absolute E, 1.75 mm filament)",
        "; printer: delta, print radius 135 mm centred at (0,0)",
    ]
    return (
        "\n".join(head)
        + "\n"
        + PREAMBLE
        + "\n".join(limits)
        + "\n"
        + "\n".join(body.lines)
        + "\n"
        + POSTAMBLE
    )


def stress_square(
    cx: float = 0.0, cy: float = 0.0, side: float = 60.0, layers: int = 10, laps: int = 2, feed: float = 9000
) -> PathWriter:
    pw = PathWriter(0.45, 0.2)
    h = side / 2
    corners = [(cx - h, cy - h), (cx + h, cy - h), (cx + h, cy + h), (cx - h, cy + h)]
    for layer in range(layers):
        z = 0.2 * (layer + 1)
        pw.comment(f"LAYER:{layer}")
        pw.travel(*corners[0], z=z, f=12000)
        if layer:
            pw.unretract(0.8)
        pw.comment("TYPE:stress square")
        first = True
        for _ in range(laps):
            for c in corners[1:] + corners[:1]:
                pw.extrude(*c, f=feed if first else None)
                first = False
        pw.retract(0.8)
    return pw


def stress_circle(
    r: float = 40.0, segments: int = 64, layers: int = 10, laps: int = 2, feed: float = 9000
) -> PathWriter:
    pw = PathWriter(0.45, 0.2)
    pts = circle(0.0, 0.0, r, segments)
    for layer in range(layers):
        z = 0.2 * (layer + 1)
        pw.comment(f"LAYER:{layer}")
        pw.travel(*pts[0], z=z, f=12000)
        if layer:
            pw.unretract(0.8)
        pw.comment("TYPE:stress circle")
        first = True
        for _ in range(laps):
            for p in list(pts[1:]) + [pts[0]]:
                pw.extrude(float(p[0]), float(p[1]), f=feed if first else None)
                first = False
        pw.retract(0.8)
    return pw


def stress_zigzag(
    length: float = 40.0, spacing: float = 0.45, layers: int = 2, feed: float = 15000
) -> PathWriter:
    pw = PathWriter(0.45, 0.2)
    n = int(round(length / spacing))  # 89 lines of 40 mm
    h = length / 2
    for layer in range(layers):
        z = 0.2 * (layer + 1)
        pw.comment(f"LAYER:{layer}")
        along_x = layer % 2 == 0

        def pt(u, v, along_x=along_x):
            return (u, v) if along_x else (v, u)

        v0 = -spacing * n / 2
        pw.travel(*pt(-h, v0), z=z, f=15000)
        if layer:
            pw.unretract(0.8)
        pw.comment("TYPE:stress zigzag")
        first = True
        for i in range(n):
            v = v0 + i * spacing
            u_end = h if i % 2 == 0 else -h
            pw.extrude(*pt(u_end, v), f=feed if first else None)
            first = False
            if i < n - 1:
                pw.extrude(*pt(u_end, v + spacing))
        pw.retract(0.8)
    return pw


ACCEL_10K = ["SET_VELOCITY_LIMIT ACCEL=10000", "M204 S10000"]


def make_stress(gdir: Path) -> list[Path]:
    write_text(
        gdir / "stress_square.gcode",
        _stress_file(
            "60 mm square centred at (0,0), sharp corners, F9000 (150 mm/s), 10000 mm/s^2",
            ACCEL_10K,
            stress_square(0.0, 0.0),
        ),
    )
    write_text(
        gdir / "stress_square_off100.gcode",
        _stress_file(
            "60 mm square centred at (100,0) (corners reach r = 133.4 mm), F9000, 10000 mm/s^2",
            ACCEL_10K,
            stress_square(100.0, 0.0),
        ),
    )
    write_text(
        gdir / "stress_circle64.gcode",
        _stress_file(
            "64-segment circle r = 40 mm centred at (0,0), F9000 (150 mm/s), 10000 mm/s^2",
            ACCEL_10K,
            stress_circle(),
        ),
    )
    write_text(
        gdir / "stress_zigzag.gcode",
        _stress_file(
            "zig-zag infill, 40 mm lines 0.45 mm apart, F15000 (250 mm/s), 10000 mm/s^2",
            ["SET_VELOCITY_LIMIT VELOCITY=300 ACCEL=10000", "M204 S10000"],
            stress_zigzag(),
        ),
    )
    return [gdir / f"stress_{n}.gcode" for n in ("square", "square_off100", "circle64", "zigzag")]


# ---------------------------------------------------------------------------------------
# Hand-written files
# ---------------------------------------------------------------------------------------
def arcs_gcode() -> str:
    k = e_per_mm(0.45, 0.3)
    e = 0.0
    out = [
        "; ffcomp hand-written sample: arcs (G17 XY plane; G2 = clockwise, G3 = counter-clockwise)",
        "; I/J = centre offset from the start point; R = radius (R<0: the arc > 180 deg).",
        "; Full circle: end point == start point with I/J. Absolute XYZ and E.",
        "; Note: Klipper's [gcode_arcs] accepts only I/J (and K); R is Marlin/RRF.",
        "G28",
        "G90",
        "M82",
        "G92 E0",
        "G17 ; XY plane",
        "G0 Z0.3 F3000",
        "G0 X-20 Y0 F9000",
    ]

    def ext(length):
        nonlocal e
        e += length * k
        return fnum(e, 5)

    r = 20.0
    out.append("; 1. semicircle CCW (through the -Y side), centre (0,0), I/J form")
    out.append(f"G3 X20 Y0 I20 J0 E{ext(math.pi * r)} F1800")
    out.append("; 2. quarter arc CW, centre (0,0), I/J form: (20,0) -> (0,-20)")
    out.append(f"G2 X0 Y-20 I-20 J0 E{ext(math.pi * r / 2)}")
    out.append("; 3. full circle CW, centre (0,0): end == start, I/J form")
    out.append(f"G2 X0 Y-20 I0 J20 E{ext(2 * math.pi * r)} F2400")
    out.append("; 4. quarter arc CCW, R form (positive R: the short arc), centre (20,-20)")
    out.append(f"G3 X20 Y-40 R20 E{ext(math.pi * r / 2)}")
    out.append("; 5. three-quarter arc CW, R form (negative R: the long arc), centre (20,-20)")
    out.append(f"G2 X40 Y-20 R-20 E{ext(1.5 * math.pi * r)}")
    out.append("; 6. small tight semicircle CCW, r = 2 mm, centre (40,-18) (high curvature)")
    out.append(f"G3 X40 Y-16 I0 J2 E{ext(math.pi * 2.0)} F3000")
    out.append("; 7. helical arc: full turn CCW, r = 10, centre (30,-16), rising 0.3 mm")
    out.append(f"G3 X40 Y-16 Z0.6 I-10 J0 E{ext(math.hypot(2 * math.pi * 10.0, 0.3))} F2400")
    out.append("; 8. straight line, then a travel arc (no E): CCW half circle, centre (0,24)")
    out.append(f"G1 X40 Y24 E{ext(40.0)}")
    out.append("G3 X-40 Y24 I-40 J0 F6000")
    out.append("; 9. no spaces between words: CCW semicircle, centre (-40,0), r = 24")
    out.append(f"G3X-40Y-24I0J-24E{ext(math.pi * 24)}F1800")
    out.append(f"G1 E{fnum(e - 0.8, 5)} F2100")
    out.append("G0 Z5 F3000")
    out.append("M84")
    return "\n".join(out) + "\n"


def klipper_limits_gcode() -> str:
    pw = PathWriter(0.45, 0.2)
    lines = [
        "; ffcomp hand-written sample: Klipper velocity/acceleration limit changes mid-file",
        "; SET_VELOCITY_LIMIT (Klipper), M204 S (accel), M220 S (speed factor %),",
        "; M221 S (flow factor %). Absolute XYZ and E.",
        "G28",
        "G90",
        "M82",
        "G92 E0",
        "SET_VELOCITY_LIMIT VELOCITY=300 ACCEL=3000 SQUARE_CORNER_VELOCITY=5 MINIMUM_CRUISE_RATIO=0.5",
        "G0 Z0.2 F3000",
    ]
    sq = [(-20, -20), (20, -20), (20, 20), (-20, 20), (-20, -20)]

    def lap(feed):
        pw.lines.clear()
        pw.travel(*sq[0], f=12000)
        for i, c in enumerate(sq[1:]):
            pw.extrude(*c, f=feed if i == 0 else None)
        return list(pw.lines)

    lines += ["; lap 1 at the start-up limits"] + lap(6000)
    lines += ["SET_VELOCITY_LIMIT ACCEL=7000", "; lap 2 after ACCEL change only"] + lap(9000)
    lines += [
        "SET_VELOCITY_LIMIT SQUARE_CORNER_VELOCITY=10 MINIMUM_CRUISE_RATIO=0.25",
        "; lap 3 after SCV / minimum cruise ratio change",
    ] + lap(9000)
    lines += [
        "M204 S2500 ; Marlin-style acceleration (Klipper: SET_VELOCITY_LIMIT ACCEL=2500)",
        "; lap 4 after M204 S",
    ] + lap(9000)
    lines += [
        "M204 P4000 T8000 ; P = print, T = travel (Klipper uses min(P,T) when S is absent)",
        "; lap 5 after M204 P/T",
    ] + lap(9000)
    lines += ["M220 S150 ; speed factor 150 %", "; lap 6 at 150 % feed rate"] + lap(6000)
    lines += ["M220 S100", "M221 S90 ; flow 90 %", "; lap 7 at 90 % flow"] + lap(6000)
    lines += [
        "M221 S100",
        "SET_VELOCITY_LIMIT VELOCITY=200 ACCEL=4000 SQUARE_CORNER_VELOCITY=5 MINIMUM_CRUISE_RATIO=0.5",
        "; lap 8 after a full SET_VELOCITY_LIMIT",
    ] + lap(9000)
    lines += [f"G1 E{fnum(pw.e - 0.8, 5)} F2100", "G0 Z5 F3000", "M84"]
    return "\n".join(lines) + "\n"


def relative_extrusion_gcode() -> str:
    k = e_per_mm(0.45, 0.2)

    def seg(a, b):
        return fnum(math.dist(a, b) * k, 5)

    sq = [(-15.0, -15.0), (15.0, -15.0), (15.0, 15.0), (-15.0, 15.0), (-15.0, -15.0)]
    lines = [
        "; ffcomp hand-written sample: relative extrusion and mode switches",
        "; M83 relative E, G91/G90 for Z-hops, G92 E0 resets, retractions, M82 back to absolute.",
        "; Firmware note: Marlin's G90 also resets E to absolute (it clears M83); Klipper's G90",
        "; leaves the M82/M83 state alone. This file re-issues M83 after every G90 so it means",
        "; the same on both.",
        "G28",
        "G90",
        "M83 ; relative E",
        "G92 E0",
        "G1 Z0.2 F3000",
        "G1 X-15 Y-15 F12000",
        "; layer 1: square, relative E per segment",
    ]
    for a, b in _pairs(sq):
        lines.append(f"G1 X{fnum(b[0])} Y{fnum(b[1])} E{seg(a, b)} F3000")
    lines += [
        "G1 E-0.8 F2100 ; retract (relative)",
        "G91 ; relative XYZ (and E)",
        "G1 Z0.4 F1200 ; Z-hop +0.4",
        "G90",
        "M83 ; re-assert relative E after G90 (Marlin resets it)",
        "G1 X0 Y0 F12000 ; travel",
        "G91",
        "G1 Z-0.4 F1200 ; drop back",
        "G90",
        "M83",
        "G1 E0.8 F2100 ; unretract",
        "G1 X10 Y0 E" + seg((0, 0), (10, 0)) + " F3000",
        "G92 E0 ; reset (no-op for relative E, common in slicer output)",
        "G1 X10 Y10 E" + seg((10, 0), (10, 10)),
        "; layer 2 (Z up via relative move)",
        "G1 E-0.8 F2100",
        "G91",
        "G1 Z0.2 F1200 ; layer change +0.2 relative",
        "G90",
        "M83",
        "G1 X-15 Y-15 F12000",
        "G1 E0.8 F2100",
    ]
    for a, b in _pairs(sq):
        lines.append(f"G1 X{fnum(b[0])} Y{fnum(b[1])} E{seg(a, b)} F3000")
    lines += [
        "; relative XY moves with extrusion under G91 (E relative too)",
        "G91",
        f"G1 X5 Y0 E{fnum(5 * k, 5)} F3000",
        f"G1 X0 Y5 E{fnum(5 * k, 5)}",
        f"G1 X-5 Y0 E{fnum(5 * k, 5)}",
        "G90",
        "M83",
        "; switch to absolute extrusion for layer 3",
        "M82",
        "G92 E0",
        "G1 E-0.8 F2100 ; absolute retract to -0.8",
        "G91",
        "G1 Z0.2 F1200",
        "G90",
        "G1 X-15 Y-15 F12000",
        "G1 E0 F2100 ; absolute unretract back to 0",
    ]
    e = 0.0
    for a, b in _pairs(sq):
        e += math.dist(a, b) * k
        lines.append(f"G1 X{fnum(b[0])} Y{fnum(b[1])} E{fnum(e, 5)} F3000")
    lines += [
        f"G1 E{fnum(e - 0.8, 5)} F2100",
        "G92 E0 ; reset absolute E",
        "G91",
        "G1 Z5 F1200",
        "G90",
        "M84",
    ]
    return "\n".join(lines) + "\n"


def checksums_gcode() -> str:
    """Host-protocol style: 'N<n> <cmd>*<xor>' with the XOR of every byte before '*'."""
    k = e_per_mm(0.45, 0.2)
    cmds = ["M110 N0", "G28", "G90", "M82", "G92 E0", "G1 Z0.2 F3000", "G1 X-10 Y-10 F9000"]
    e = 0.0
    sq = [(-10, -10), (10, -10), (10, 10), (-10, 10), (-10, -10)]
    for a, b in _pairs(sq):
        e += math.dist(a, b) * k
        cmds.append(f"G1 X{b[0]} Y{b[1]} E{fnum(e, 5)} F3000")
    cmds += [f"G1 E{fnum(e - 0.8, 5)} F2100", "G1 Z5 F3000", "M84"]
    out = [
        "; ffcomp hand-written sample: line numbers and checksums (Marlin host protocol)",
        "; checksum = XOR of all bytes of the line before '*'; N0 M110 N0 resets the counter",
    ]
    for n, c in enumerate(cmds):
        body = f"N{n} {c}"
        out.append(f"{body}*{gcode_checksum(body)}")
    return "\n".join(out) + "\n"


def out_of_radius_gcode() -> str:
    k = e_per_mm(0.45, 0.2)
    e1 = 100.0 * k
    e2 = e1 + math.dist((100, 0), (110, 80)) * k  # r(110, 80) = 136.0 mm > 135 mm
    return (
        "\n".join(
            [
                "; ffcomp hand-written sample: one move leaves the 135 mm print radius",
                "; the G1 to X110 Y80 ends at r = 136.0 mm (everything else is inside)",
                "G28",
                "G90",
                "M82",
                "G92 E0",
                "G1 Z0.2 F3000",
                "G1 X0 Y0 F9000",
                f"G1 X100 Y0 E{fnum(e1, 5)} F3000",
                f"G1 X110 Y80 E{fnum(e2, 5)} ; r = 136.0 mm: outside the print radius",
                "G1 X0 Y0 F9000",
                "G1 Z5",
                "M84",
            ]
        )
        + "\n"
    )


def malformed_gcode() -> str:
    return (
        "\n".join(
            [
                "; ffcomp hand-written sample: one malformed line (letter O instead of zero)",
                "G28",
                "G90",
                "M82",
                "G92 E0",
                "G1 Z0.2 F3000",
                "G1 X10 Y0 F6000",
                "G1 X1O Y5 ; malformed: 'X1O' (line 8)",
                "G1 X0 Y0",
                "M84",
            ]
        )
        + "\n"
    )


def make_hand(gdir: Path) -> list[Path]:
    files = {
        "arcs": arcs_gcode,
        "klipper_limits": klipper_limits_gcode,
        "relative_extrusion": relative_extrusion_gcode,
        "checksums": checksums_gcode,
        "out_of_radius": out_of_radius_gcode,
        "malformed": malformed_gcode,
    }
    paths = []
    for name, fn in files.items():
        paths.append(gdir / f"{name}.gcode")
        write_text(paths[-1], fn())
    return paths


# ---------------------------------------------------------------------------------------
# PrusaSlicer
# ---------------------------------------------------------------------------------------
PRUSA_START = "G28 ; home all towers (delta)\nG1 Z5 F5000 ; lift nozzle\nG92 E0"
PRUSA_END = "M104 S0 ; hotend off\nM140 S0 ; bed off\nM107\nG91\nG1 Z5 F1200\nG90\nG28 ; park at the top\nM84"


def _opts(text: str) -> list[str]:
    """'--a 1 --b 2' -> ['--a', '1', '--b', '2'] (for values without spaces)."""
    return text.split()


# Delta printer + filament + machine limits + speeds, common to every PrusaSlicer run.
PRUSA_PRINTER = _opts(
    f"""
    --max-print-height {fnum(PRINT_HEIGHT_MM)} --nozzle-diameter {fnum(NOZZLE_MM)}
    --filament-diameter {fnum(FILAMENT_MM)} --gcode-flavor marlin2
    --machine-limits-usage emit_to_gcode
    --machine-max-acceleration-x 10000 --machine-max-acceleration-y 10000
    --machine-max-acceleration-z 10000 --machine-max-acceleration-e 10000
    --machine-max-acceleration-extruding 5000 --machine-max-acceleration-retracting 5000
    --machine-max-acceleration-travel 7000
    --machine-max-feedrate-x 300 --machine-max-feedrate-y 300 --machine-max-feedrate-z 300
    --machine-max-feedrate-e 120
    --machine-max-jerk-x 10 --machine-max-jerk-y 10 --machine-max-jerk-z 10 --machine-max-jerk-e 5
    --temperature 210 --first-layer-temperature 215
    --bed-temperature 60 --first-layer-bed-temperature 60
    """
)
PRUSA_MOTION = _opts(
    """
    --retract-length 0.8 --retract-speed 35 --retract-lift 0.2
    --travel-speed 200 --perimeter-speed 60 --external-perimeter-speed 40 --infill-speed 100
    --solid-infill-speed 80 --top-solid-infill-speed 50 --gap-fill-speed 40
    --first-layer-speed 25 --bridge-speed 40
    --default-acceleration 3000 --perimeter-acceleration 2000 --infill-acceleration 4000
    --bridge-acceleration 2000 --first-layer-acceleration 1000
    --skirts 1 --skirt-distance 4 --brim-width 0 --gcode-label-objects
    """
)


def prusa_printer_args() -> list[str]:
    """Delta printer + filament + machine limits, common to every PrusaSlicer run."""
    return (
        ["--bed-shape", bed_shape_arg()]
        + PRUSA_PRINTER
        + ["--start-gcode", PRUSA_START, "--end-gcode", PRUSA_END]
        + PRUSA_MOTION
    )


# per-sample print settings (coarse for the committed samples)
PRUSA_JOBS = {
    "cube_prusa": (
        "cube20",
        _opts(
            "--layer-height 0.3 --first-layer-height 0.3 --perimeters 2 --top-solid-layers 3"
            " --bottom-solid-layers 3 --fill-density 15% --fill-pattern rectilinear"
        ),
    ),
    # the cube again with "wipe while retracting": the nozzle moves back along the last perimeter
    # while it retracts (retracting XY moves, which Klipper caps by the extruder's limits)
    "cube_wipe_prusa": (
        "cube20",
        _opts(
            "--layer-height 0.3 --first-layer-height 0.3 --perimeters 2 --top-solid-layers 3"
            " --bottom-solid-layers 3 --fill-density 15% --fill-pattern rectilinear --wipe"
        ),
    ),
    # the cube with firmware retraction (G10/G11; a profile without [firmware_retraction] plans
    # them as stops, every stream after one starts with a pre-roll from rest)
    "cube_fwr_prusa": (
        "cube20",
        _opts(
            "--layer-height 0.3 --first-layer-height 0.3 --perimeters 2 --top-solid-layers 3"
            " --bottom-solid-layers 3 --fill-density 15% --fill-pattern rectilinear"
            " --use-firmware-retraction"
        ),
    ),
    "ringing_tower_prusa": (
        "ringing_tower_6mm",
        _opts("--layer-height 0.3 --first-layer-height 0.3 --perimeters 2 --fill-density 0%"),
    ),
    "cylinder_prusa": (
        "cylinder40x30",
        # relative E: PrusaSlicer refuses it unless layer_gcode resets E ("G92 E0")
        _opts(
            "--layer-height 0.3 --first-layer-height 0.3 --perimeters 2 --top-solid-layers 3"
            " --bottom-solid-layers 3 --fill-density 10% --fill-pattern grid"
            " --use-relative-e-distances"
        )
        + ["--layer-gcode", "G92 E0"],
    ),
    # spiral vase (deltas' classic): one perimeter whose z rises all along every layer, no retraction
    "vase_prusa": (
        "cylinder40x30",
        _opts(
            "--layer-height 0.3 --first-layer-height 0.3 --perimeters 1 --top-solid-layers 0"
            " --bottom-solid-layers 3 --fill-density 0% --spiral-vase"
        ),
    ),
}
PRUSA_PLATE_ARGS = _opts(
    "--layer-height 0.3 --first-layer-height 0.3 --perimeters 2 --top-solid-layers 4"
    " --bottom-solid-layers 3 --fill-density 15% --fill-pattern rectilinear"
)


def find_prusa(explicit: str | None) -> str | None:
    return explicit or shutil.which("prusa-slicer") or shutil.which("prusa-slicer-console")


def run_prusa(
    exe: str, stls: list[Path], out: Path, extra: list[str], merge: bool = False
) -> tuple[list[str], float]:
    cmd = [exe, "--export-gcode", "--loglevel", "1"] + prusa_printer_args() + extra
    # Transforms run in command-line order: a --center before --merge would centre every
    # object on (0,0) before merging (they would all overlap). The plate's STLs already sit
    # at their bed positions, so the plate is merged without re-arranging or centring.
    cmd += ["--merge", "--dont-arrange"] if merge else ["--center", "0,0"]
    cmd += ["--output", str(out)] + [str(p) for p in stls]
    out.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    dt = time.perf_counter() - t0
    if proc.returncode != 0 or not out.exists():
        raise RuntimeError(f"prusa-slicer failed ({proc.returncode}):\n{proc.stdout}\n{proc.stderr}")
    return cmd, dt


# ---------------------------------------------------------------------------------------
# CuraEngine
# ---------------------------------------------------------------------------------------
CURA_DEF_SEARCH = [
    "/usr/share/cura/resources/definitions",
    "/usr/share/cura-engine/resources/definitions",
    "/usr/local/share/cura/resources/definitions",
]


def find_fdmprinter(explicit: str | None) -> Path | None:
    """--fdmprinter, else $FFCOMP_FDMPRINTER, else the Debian/Ubuntu `cura` package's copy."""
    if explicit:
        return Path(explicit) if Path(explicit).is_file() else None
    cands = [os.environ.get("FFCOMP_FDMPRINTER")] + [f"{d}/fdmprinter.def.json" for d in CURA_DEF_SEARCH]
    for c in cands:
        if c and Path(c).is_file():
            return Path(c)
    return None


def cura_delta_definition() -> dict:
    """Machine definition for the delta (loaded after fdmprinter.def.json with -j)."""

    def dv(v):
        return {"default_value": v}

    return {
        "version": 2,
        "name": "ffcomp delta R135",
        "inherits": "fdmprinter",
        "metadata": {"visible": False, "machine_extruder_trains": {"0": "fdmextruder"}},
        "overrides": {
            "machine_name": dv("ffcomp delta R135"),
            "machine_center_is_zero": dv(True),
            "machine_shape": dv("elliptic"),
            "machine_width": dv(270),
            "machine_depth": dv(270),
            "machine_height": dv(300),
            "machine_heated_bed": dv(True),
            "machine_nozzle_size": dv(0.4),
            "material_diameter": dv(1.75),
            "machine_gcode_flavor": dv("RepRap (Marlin/Sprinter)"),
            "machine_start_gcode": dv("G28 ;home all towers (delta)\nG1 Z5 F5000\nG92 E0"),
            "machine_end_gcode": dv(
                "M104 S0\nM140 S0\nM107\nG91\nG1 Z5 F1200\nG90\nG28 ;park at the top\nM84"
            ),
            "machine_max_acceleration_x": dv(10000),
            "machine_max_acceleration_y": dv(10000),
            "machine_max_acceleration_z": dv(10000),
            "machine_max_feedrate_x": dv(300),
            "machine_max_feedrate_y": dv(300),
            "machine_max_feedrate_z": dv(300),
        },
    }


CURA_CUBE_SETTINGS = {
    # CuraEngine evaluates no "value" formulas: every derived setting is given explicitly
    "layer_height": 0.3,
    "layer_height_0": 0.3,
    "line_width": 0.4,
    "wall_line_width": 0.4,
    "wall_line_width_0": 0.4,
    "wall_line_width_x": 0.4,
    "skin_line_width": 0.4,
    "infill_line_width": 0.4,
    "skirt_brim_line_width": 0.4,
    "initial_layer_line_width_factor": 100,
    "wall_thickness": 0.8,
    "wall_line_count": 2,
    "top_bottom_thickness": 0.9,
    "top_thickness": 0.9,
    "bottom_thickness": 0.9,
    "top_layers": 3,
    "bottom_layers": 3,
    "infill_sparse_density": 15,
    "infill_pattern": "grid",
    "infill_line_distance": 0.4 * 100 / 15 * 2,
    "speed_print": 60,
    "speed_infill": 80,
    "speed_wall": 40,
    "speed_wall_0": 30,
    "speed_wall_x": 50,
    "speed_topbottom": 40,
    "speed_travel": 150,
    "speed_layer_0": 25,
    "speed_print_layer_0": 25,
    "speed_travel_layer_0": 100,
    "acceleration_enabled": True,
    "acceleration_print": 3000,
    "acceleration_infill": 4000,
    "acceleration_wall": 2000,
    "acceleration_wall_0": 2000,
    "acceleration_wall_x": 2000,
    "acceleration_topbottom": 3000,
    "acceleration_travel": 5000,
    "acceleration_layer_0": 1000,
    "acceleration_print_layer_0": 1000,
    "acceleration_travel_layer_0": 1000,
    "acceleration_skirt_brim": 1000,
    "material_print_temperature": 210,
    "material_print_temperature_layer_0": 215,
    "material_initial_print_temperature": 210,
    "material_final_print_temperature": 205,
    "material_bed_temperature": 60,
    "material_bed_temperature_layer_0": 60,
    "retraction_enable": True,
    "retraction_amount": 0.8,
    "retraction_speed": 35,
    "retraction_retract_speed": 35,
    "retraction_prime_speed": 35,
    "retraction_hop_enabled": True,
    "retraction_hop": 0.2,
    "adhesion_type": "skirt",
    "skirt_line_count": 1,
    "skirt_gap": 4,
}
CURA_EXTRUDER_SETTINGS = {"material_diameter": FILAMENT_MM, "machine_nozzle_size": NOZZLE_MM}


def _cura_s(settings: dict) -> list[str]:
    args = []
    for key, val in settings.items():
        v = str(val).lower() if isinstance(val, bool) else str(val)
        args += ["-s", f"{key}={v}"]
    return args


def run_cura(
    exe: str, fdmprinter: Path, delta_def: Path, stl: Path, out: Path, settings: dict, extruder_settings: dict
) -> tuple[list[str], float]:
    defs = fdmprinter.resolve().parent
    delta_def = delta_def.resolve()
    extruders = defs.parent / "extruders"
    env = dict(os.environ)
    env["CURA_ENGINE_SEARCH_PATH"] = os.pathsep.join(str(p) for p in (defs, extruders, delta_def.parent))
    # -s before -e0: global settings; -s after -e0: extruder 0 (material_diameter and the
    # nozzle live in fdmextruder.def.json, so a global -s does not reach them); -l after -e0
    # puts the mesh on extruder 0.
    cmd = [exe, "slice", "-j", str(fdmprinter), "-j", str(delta_def)] + _cura_s(settings)
    # run in the model's folder with a bare file name: Cura writes it into every ;MESH: line
    cmd += ["-e0"] + _cura_s(extruder_settings) + ["-l", stl.name, "-o", str(out.resolve())]
    out.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=stl.parent)
    dt = time.perf_counter() - t0
    if proc.returncode != 0 or not out.exists() or out.stat().st_size == 0:
        raise RuntimeError(f"CuraEngine failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    return cmd, dt


# ---------------------------------------------------------------------------------------
# main
# ---------------------------------------------------------------------------------------
def _fmt_cmd(cmd: list[str]) -> str:
    return " ".join(shlex.quote(c) for c in cmd)


def _report(path: Path) -> str:
    with open(path, "rb") as f:
        n = sum(1 for _ in f)
    return f"{path.name}: {n} lines, {path.stat().st_size / 1024:.0f} KiB"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--outdir", type=Path, default=HERE, help="root for models/, gcode/ and large/ (default: this folder)"
    )
    ap.add_argument(
        "--large", action="store_true", help="also slice the multi-object plate into large/plate_prusa.gcode"
    )
    ap.add_argument(
        "--large-only", action="store_true", help="only the plate models and large/plate_prusa.gcode"
    )
    ap.add_argument("--no-slice", action="store_true", help="skip every slicer run")
    ap.add_argument("--prusa-slicer", help="path to prusa-slicer (default: from PATH)")
    ap.add_argument("--cura-engine", help="path to CuraEngine (default: from PATH)")
    ap.add_argument("--fdmprinter", help="path to Cura's fdmprinter.def.json")
    ap.add_argument("--print-commands", action="store_true", help="print slicer command lines")
    args = ap.parse_args(argv)

    outdir: Path = args.outdir
    models_dir, gdir, ldir = outdir / "models", outdir / "gcode", outdir / "large"
    produced: list[Path] = []
    failures = 0
    prusa = None if args.no_slice else find_prusa(args.prusa_slicer)

    if not args.large_only:
        models = make_models(models_dir)
        print(f"models: {', '.join(p.name for p in models.values())} -> {models_dir}")
        produced += make_hand(gdir) + make_stress(gdir)

        if not args.no_slice:
            if prusa is None:
                print(
                    "SKIP PrusaSlicer samples: prusa-slicer not found (apt-get install prusa-slicer)",
                    file=sys.stderr,
                )
            else:
                for name, (model, extra) in PRUSA_JOBS.items():
                    out = gdir / f"{name}.gcode"
                    try:
                        cmd, dt = run_prusa(prusa, [models[model]], out, extra)
                        print(f"prusa-slicer {name}: {dt:.1f} s")
                        if args.print_commands:
                            print("  " + _fmt_cmd(cmd))
                        produced.append(out)
                    except RuntimeError as exc:
                        failures += 1
                        print(f"FAILED {name}: {exc}", file=sys.stderr)

            cura = args.cura_engine or shutil.which("CuraEngine")
            fdm = find_fdmprinter(args.fdmprinter)
            if cura is None or fdm is None:
                print(
                    "SKIP Cura samples: "
                    + (
                        "CuraEngine not found (apt-get install cura-engine)"
                        if cura is None
                        else "fdmprinter.def.json not found (apt-get install cura, or pass --fdmprinter)"
                    ),
                    file=sys.stderr,
                )
            else:
                delta_def = models_dir / "ffcomp_delta.def.json"
                delta_def.write_text(json.dumps(cura_delta_definition(), indent=2) + "\n")
                out = gdir / "cube_cura.gcode"
                try:
                    cmd, dt = run_cura(
                        cura,
                        fdm,
                        delta_def,
                        models["cube20"],
                        out,
                        CURA_CUBE_SETTINGS,
                        CURA_EXTRUDER_SETTINGS,
                    )
                    print(f"CuraEngine cube_cura: {dt:.1f} s")
                    if args.print_commands:
                        print("  " + _fmt_cmd(cmd))
                    produced.append(out)
                except RuntimeError as exc:
                    failures += 1
                    print(f"FAILED cube_cura: {exc}", file=sys.stderr)

    if args.large or args.large_only:
        plate = make_plate_models(models_dir / "plate")
        if args.no_slice:
            pass
        elif prusa is None:
            print("SKIP large/plate_prusa.gcode: prusa-slicer not found", file=sys.stderr)
        else:
            out = ldir / "plate_prusa.gcode"
            try:
                cmd, dt = run_prusa(prusa, plate, out, PRUSA_PLATE_ARGS, merge=True)
                print(f"prusa-slicer plate_prusa: {dt:.1f} s")
                if args.print_commands:
                    print("  " + _fmt_cmd(cmd))
                produced.append(out)
            except RuntimeError as exc:
                failures += 1
                print(f"FAILED plate_prusa: {exc}", file=sys.stderr)

    for p in produced:
        print("  " + _report(p))
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())

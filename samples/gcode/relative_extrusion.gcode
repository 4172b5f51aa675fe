; ffcomp hand-written sample: relative extrusion and mode switches
; M83 relative E, G91/G90 for Z-hops, G92 E0 resets, retractions, M82 back to absolute.
; Firmware note: Marlin's G90 also resets E to absolute (it clears M83); Klipper's G90
; leaves the M82/M83 state alone. This file re-issues M83 after every G90 so it means
; the same on both.
G28
G90
M83 ; relative E
G92 E0
G1 Z0.2 F3000
G1 X-15 Y-15 F12000
; layer 1: square, relative E per segment
G1 X15 Y-15 E1.12253 F3000
G1 X15 Y15 E1.12253 F3000
G1 X-15 Y15 E1.12253 F3000
G1 X-15 Y-15 E1.12253 F3000
G1 E-0.8 F2100 ; retract (relative)
G91 ; relative XYZ (and E)
G1 Z0.4 F1200 ; Z-hop +0.4
G90
M83 ; re-assert relative E after G90 (Marlin resets it)
G1 X0 Y0 F12000 ; travel
G91
G1 Z-0.4 F1200 ; drop back
G90
M83
G1 E0.8 F2100 ; unretract
G1 X10 Y0 E0.37418 F3000
G92 E0 ; reset (no-op for relative E, common in slicer output)
G1 X10 Y10 E0.37418
; layer 2 (Z up via relative move)
G1 E-0.8 F2100
G91
G1 Z0.2 F1200 ; layer change +0.2 relative
G90
M83
G1 X-15 Y-15 F12000
G1 E0.8 F2100
G1 X15 Y-15 E1.12253 F3000
G1 X15 Y15 E1.12253 F3000
G1 X-15 Y15 E1.12253 F3000
G1 X-15 Y-15 E1.12253 F3000
; relative XY moves with extrusion under G91 (E relative too)
G91
G1 X5 Y0 E0.18709 F3000
G1 X0 Y5 E0.18709
G1 X-5 Y0 E0.18709
G90
M83
; switch to absolute extrusion for layer 3
M82
G92 E0
G1 E-0.8 F2100 ; absolute retract to -0.8
G91
G1 Z0.2 F1200
G90
G1 X-15 Y-15 F12000
G1 E0 F2100 ; absolute unretract back to 0
G1 X15 Y-15 E1.12253 F3000
G1 X15 Y15 E2.24506 F3000
G1 X-15 Y15 E3.36759 F3000
G1 X-15 Y-15 E4.49012 F3000
G1 E3.69012 F2100
G92 E0 ; reset absolute E
G91
G1 Z5 F1200
G90
M84

; ffcomp hand-written sample: arcs (G17 XY plane; G2 = clockwise, G3 = counter-clockwise)
; I/J = centre offset from the start point; R = radius (R<0: the arc > 180 deg).
; Full circle: end point == start point with I/J. Absolute XYZ and E.
; Note: Klipper's [gcode_arcs] accepts only I/J (and K); R is Marlin/RRF.
G28
G90
M82
G92 E0
G17 ; XY plane
G0 Z0.3 F3000
G0 X-20 Y0 F9000
; 1. semicircle CCW (through the -Y side), centre (0,0), I/J form
G3 X20 Y0 I20 J0 E3.52653 F1800
; 2. quarter arc CW, centre (0,0), I/J form: (20,0) -> (0,-20)
G2 X0 Y-20 I-20 J0 E5.2898
; 3. full circle CW, centre (0,0): end == start, I/J form
G2 X0 Y-20 I0 J20 E12.34286 F2400
; 4. quarter arc CCW, R form (positive R: the short arc), centre (20,-20)
G3 X20 Y-40 R20 E14.10612
; 5. three-quarter arc CW, R form (negative R: the long arc), centre (20,-20)
G2 X40 Y-20 R-20 E19.39592
; 6. small tight semicircle CCW, r = 2 mm, centre (40,-18) (high curvature)
G3 X40 Y-16 I0 J2 E19.74857 F3000
; 7. helical arc: full turn CCW, r = 10, centre (30,-16), rising 0.3 mm
G3 X40 Y-16 Z0.6 I-10 J0 E23.27514 F2400
; 8. straight line, then a travel arc (no E): CCW half circle, centre (0,24)
G1 X40 Y24 E25.5202
G3 X-40 Y24 I-40 J0 F6000
; 9. no spaces between words: CCW semicircle, centre (-40,0), r = 24
G3X-40Y-24I0J-24E29.75204F1800
G1 E28.95204 F2100
G0 Z5 F3000
M84

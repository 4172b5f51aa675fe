; ffcomp hand-written sample: one malformed line (letter O instead of zero)
G28
G90
M82
G92 E0
G1 Z0.2 F3000
G1 X10 Y0 F6000
G1 X1O Y5 ; malformed: 'X1O' (line 8)
G1 X0 Y0
M84

; ffcomp hand-written sample: one move leaves the 135 mm print radius
; the G1 to X110 Y80 ends at r = 136.0 mm (everything else is inside)
G28
G90
M82
G92 E0
G1 Z0.2 F3000
G1 X0 Y0 F9000
G1 X100 Y0 E3.74177 F3000
G1 X110 Y80 E6.75847 ; r = 136.0 mm: outside the print radius
G1 X0 Y0 F9000
G1 Z5
M84

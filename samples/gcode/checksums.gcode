; ffcomp hand-written sample: line numbers and checksums (Marlin host protocol)
; checksum = XOR of all bytes of the line before '*'; N0 M110 N0 resets the counter
N0 M110 N0*125
N1 G28*18
N2 G90*18
N3 M82*26
N4 G92 E0*67
N5 G1 Z0.2 F3000*30
N6 G1 X-10 Y-10 F9000*64
N7 G1 X10 Y-10 E0.74835 F3000*32
N8 G1 X10 Y10 E1.49671 F3000*3
N9 G1 X-10 Y10 E2.24506 F3000*36
N10 G1 X-10 Y-10 E2.99341 F3000*50
N11 G1 E2.19341 F2100*58
N12 G1 Z5 F3000*49
N13 M84*45

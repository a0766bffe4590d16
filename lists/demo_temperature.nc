; geo-server default machine - temperature compensation test program
; Adapted from 000_f9d45d2c9c541e3b.txt p.24 / §3.3 (TF5200 Axis compensation EN v1.51):
;   N10: G90 G01 X0 F1000 / G04 1 / N10 X100 / G04 1 / N10 X80 / G04 1 / N10 X50 /
;   G04 1 / N20 X-200 / G04 1 / $GOTO [N10] / M30
; Changes: X is homed first (TEMPC is only effective on a homed axis, 000 §3),
; block numbers are unique, "N10:" is written "N10". The moves stay inside the X travel
; of the default machine (-500 .. +500 mm). X uses the manual's example parameters
; (achsmd1.lis: position_0 100, offset_0 40, coefficient 4000 µm/m, n_cycles 20).
; The program loops for ever like the manual's test; stop it with a reset.
N05 G74 X1                ; home X
N10 G90 G01 X0 F1000      ; absolute, linear, 1000 mm/min
N15 G04 1                 ; dwell 1 s
N20 X100
N25 G04 1
N30 X80
N35 G04 1
N40 X50
N45 G04 1
N50 X-200
N55 G04 1
N60 $GOTO [N10]
N65 M30

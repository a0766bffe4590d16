; Source: 000_f9d45d2c9c541e3b.txt (TF5200 Axis compensation EN v1.51) p.24 / §3.3 — NC program used for the temperature test
N10: G90 G01 X0 F1000
G04 1
N10 X100
G04 1
N10 X80
G04 1
N10 X50
G04 1
N20 X-200
G04 1
$GOTO [N10]
M30

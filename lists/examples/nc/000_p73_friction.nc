; Source: 000_f9d45d2c9c541e3b.txt (TF5200 Axis compensation EN v1.51) p.73 / §4.5.1.3.1 — COMP ON/OFF FRICT
N15 X[COMP ON FRICT] ;Activates X axis
N25 Y[COMP OFF FRICT] ;Deactivates Y axis
N35 X22 Y33 Z44
N45 X[COMP OFF FRICT] ;Deactivates X axis
N55 M30 ;Program end

; Source: 001_dfb54e5cb1ca258d.txt (TF5200 Achskompensationen DE) §3.3 Beispiel (~p.26) — NC-Programm des Tests ($GOTO N10 without brackets)
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

$GOTO N10
M30

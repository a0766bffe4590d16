; Source: 001_dfb54e5cb1ca258d.txt (TF5200 Achskompensationen DE) §5.1 (~p.76) — COMP axis-specific programming
;Ausschalten von Kreuz- und Flächenkompensation in der X-Achse
N10 X[COMP OFF CROSS PLANE]

;Kompensationsprogrammierung mehrerer Achsen in einem NC-Satz
N50 X[COMP OFF CROSS] Y[COMP ON LEAD TEMP]

;Ausschalten aller Kompensationen in der Z-Achse
N100 Z[COMP OFF_ALL]

;Ausschalten aller Kompensationen der Y-Achse ohne Achsbewegung
N200 Y[COMP OFF_ALL NO_MOVE]

; Source: 000_f9d45d2c9c541e3b.txt (TF5200 Axis compensation EN v1.51) p.94 / §5.1 — axis-specific programming of COMP (missing "]" in N10 as printed)
;Deactivate cross and plane compensation in the X axis
N10 X[COMP OFF CROSS PLANE
;Compensation programming of multiple axes in an NC block
N50 X[COMP OFF CROSS] Y[COMP ON LEAD TEMP]
;Deactivate all compensations in the Z axis
N100 Z[COMP OFF_ALL]
;Deactivate all compensations of the Y axis without axis motion
N200 Y[COMP OFF_ALL NO_MOVE]

; Source: 001_dfb54e5cb1ca258d.txt (TF5200 Achskompensationen DE) §5.2 (~p.77) — Prüfen der Zustände der Achskompensation
N010 G74 X1 Y2 Z3
N020 $IF V.A.CROSS_COMP_INIT.X != TRUE
N030 #MSG ["Cross_Comp for X not init."]
N040 $ENDIF
N050 $IF V.A.TEMP_COMP_INIT.X != TRUE
N060 #MSG ["Temp_Comp for X not init."]
N070 $ENDIF
N080 X [ COMP ON CROSS TEMP ]
N090 $IF V.A.CROSS_COMP_ACTIVE[0] != TRUE
N100 #MSG ["Cross_Comp for X not active"]
N110 $ENDIF
N120 $IF V.A.TEMP_COMP_ACTIVE[0] != TRUE
N130 #MSG ["Temp_Comp for X not active"]
N140 $ENDIF
N150 ...

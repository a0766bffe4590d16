; Source: 000_f9d45d2c9c541e3b.txt (TF5200 Axis compensation EN v1.51) p.96 / §5.2 — check the states of the axis compensation (spaces in "V. A." as extracted)
N010 G74 X1 Y2 Z3
N020 $IF V. A. CROSS_COMP_INIT. X != TRUE
N030 #MSG ["Cross_Comp for X not init."]
N040 $ENDIF
N050 $IF V. A. TEMP_COMP_INIT. X != TRUE
N060 #MSG ["Temp_Comp for X not init."]
N070 $ENDIF
N080 X [ COMP ON CROSS TEMP ]
N090 $IF V. A. CROSS_COMP_ACTIVE[0] != TRUE
N100 #MSG ["Cross_Comp for X not active"]
N110 $ENDIF
N120 $IF V. A. TEMP_COMP_ACTIVE[0] != TRUE
N130 #MSG ["Temp_Comp for X not active"]
N140 $ENDIF
N150 ...

"""The dual-EPM rig (seed 003): two KUKA LBR arms carrying permanent magnets and a Hall board.

`run`: the field-sequence program on the one run engine (`FieldSequenceRun`); `actuators`: the two
arms as one actuator group (`ArmPair`); `motion`: where the servo targets come from (the approach,
the plan, holds and rejoins); `sensors`: the Hall board's samples and eq. 24; `metrics`: seed 003
Table 1 and Fig. 6.
"""

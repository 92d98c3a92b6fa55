"""The thesis's numerical examples, with every printed quantity and documented typo fixes, and
`flexible_drive` and `two_area_power`, models of our own (not from the thesis) for the tuning benchmarks."""

from ._base import ThesisExample as ThesisExample
from ._chapter3 import (
    example_3_1_2 as example_3_1_2,
    example_3_1_3 as example_3_1_3,
    example_3_3_7 as example_3_3_7,
)
from ._chapter4 import (
    example_4_1_3 as example_4_1_3,
    example_4_2_2 as example_4_2_2,
    example_4_3_2 as example_4_3_2,
    example_4_4_2 as example_4_4_2,
)
from ._drive import flexible_drive as flexible_drive
from ._motor import electrical_motor as electrical_motor
from ._power import two_area_power as two_area_power
from ._robot_arm import robot_arm as robot_arm, robot_arm_ts as robot_arm_ts

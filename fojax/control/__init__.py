"""Observer-based control and fault-tolerant control of descriptor systems (thesis Chapter 4):
state feedback, closed loops, fault-tolerant designs and the finite-time loop."""

from ..simulation._discretize import simulate_lti as simulate_lti
from ._feedback import (
    design_state_feedback as design_state_feedback,
    StateFeedbackDesign as StateFeedbackDesign,
)
from ._finite_time import (
    finite_time_loop as finite_time_loop,
    FiniteTimeLoop as FiniteTimeLoop,
    FiniteTimeTrajectory as FiniteTimeTrajectory,
)
from ._ftc import (
    design_actuator_ftc as design_actuator_ftc,
    design_sensor_ftc as design_sensor_ftc,
    design_simultaneous_ftc as design_simultaneous_ftc,
    FaultTolerantControl as FaultTolerantControl,
    FTCTrajectory as FTCTrajectory,
)
from ._loop import (
    assemble as assemble,
    closed_loop as closed_loop,
    loop_maps as loop_maps,
    LoopMaps as LoopMaps,
)

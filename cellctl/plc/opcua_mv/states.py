"""The two state machines of OPC 40100-1 as the cell drives them (pure logic, no OPC UA).

``VisionStateMachine``: ``Preoperational`` while the server starts and right after ``Reset``;
``Halted`` after ``Halt`` until ``Reset``; ``Error`` while a device the cell needs is unreachable or
the robot is latched by a Stop (the reason is ``SystemState.StateDescription``); else ``Operational``.

``AutomaticModeStateMachine`` (a sub-state machine of ``Operational``, active after
``SelectModeAutomatic``; left by ``Halt``): ``Initialized`` until a recipe is prepared, ``Ready``,
``SingleExecution`` while a ``StartSingleJob`` runs, ``ContinuousExecution`` while a production run
started by ``StartContinuous`` runs. Outside ``Operational`` or before the mode is selected its
``CurrentState`` is null.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

VisionState = Literal["Preoperational", "Halted", "Error", "Operational"]
AutoState = Literal["Initialized", "Ready", "SingleExecution", "ContinuousExecution"]
Job = Literal["single", "continuous"]

# The states' nodes in the NodeSet (namespace MachineVision): CurrentState/Id points at them.
VISION_STATE_IDS: dict[VisionState, int] = {"Preoperational": 5028, "Halted": 5029, "Error": 5030,
                                            "Operational": 5031}
AUTO_STATE_IDS: dict[AutoState, int] = {"Initialized": 5056, "Ready": 5057, "SingleExecution": 5058,
                                        "ContinuousExecution": 5059}
# SystemStateDataType (SEMI E10 words): production, stand by, unscheduled and non-scheduled downtime.
SYSTEM_PRODUCTION, SYSTEM_STANDBY, SYSTEM_UNSCHEDULED_DOWN, SYSTEM_NONSCHEDULED = 1, 2, 5, 6


@dataclass
class VisionModel:
    """What the PLC has done to the vision system; the cell's condition is passed in (``problem``)."""

    starting: bool = True
    halted: bool = False
    automatic: bool = False
    prepared: int | None = None
    """The prepared recipe's number (None: none)."""
    job: Job | None = None

    def vision_state(self, problem: str | None) -> VisionState:
        if self.halted:
            return "Halted"
        if self.starting:
            return "Preoperational"
        return "Error" if problem else "Operational"

    def auto_state(self, problem: str | None) -> AutoState | None:
        if not self.automatic or self.vision_state(problem) != "Operational" and self.job is None:
            return None
        if self.job == "single":
            return "SingleExecution"
        if self.job == "continuous":
            return "ContinuousExecution"
        return "Ready" if self.prepared is not None else "Initialized"

    def system_state(self, problem: str | None) -> tuple[int, str]:
        """``SystemState``: (SystemStateDataType value, description)."""
        state = self.vision_state(problem)
        if state == "Halted":
            return SYSTEM_NONSCHEDULED, "halted by the PLC (Halt): Reset to start again"
        if state == "Error":
            return SYSTEM_UNSCHEDULED_DOWN, problem or "error"
        if state == "Preoperational":
            return SYSTEM_NONSCHEDULED, "starting"
        return (SYSTEM_PRODUCTION, "working on a job") if self.job else (SYSTEM_STANDBY, "ready")

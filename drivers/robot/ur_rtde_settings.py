"""The settings of the UR adapter (``kind: ur_rtde``) and the controller's mode names (``drivers/robot/ur_rtde.py``)."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field

ROBOT_MODES = {
    -1: "no_controller",
    0: "disconnected",
    1: "confirm_safety",
    2: "booting",
    3: "power_off",
    4: "power_on",
    5: "idle",
    6: "backdrive",
    7: "running",
    8: "updating_firmware",
}
SAFETY_MODES = {
    1: "normal",
    2: "reduced",
    3: "protective_stop",
    4: "recovery",
    5: "safeguard_stop",
    6: "system_emergency_stop",
    7: "robot_emergency_stop",
    8: "violation",
    9: "fault",
    10: "validate_joint_id",
    11: "undefined_safety_mode",
}


class URRTDESettings(BaseModel):
    """Settings of a Universal Robots arm reached over RTDE."""

    model_config = ConfigDict(extra="forbid")

    host: str = Field(min_length=1, description="controller IP address or host name")
    frequency_hz: float = Field(500.0, gt=0, le=500, description="RTDE rate: 500 e-Series, 125 CB3")
    state_max_age_s: float = Field(0.1, gt=0, le=10, description="older samples are never served as current")
    connect_timeout_s: float = Field(5.0, gt=0, le=120, description="first connection: wait for the first sample")
    reconnect_wait_s: float = Field(
        2.5, gt=0, le=120,
        description="a later connect() (after an outage) waits at most this (under the service's 3 s device "
        "deadline); the adapter keeps retrying in the background anyway",
    )
    stall_timeout_s: float = Field(
        1.0, gt=0, le=60, description="no new sample for this long: the connection is restarted"
    )
    command_timeout_s: float = Field(
        10.0, gt=0, le=600, description="deadline of a control request, added to a move's duration"
    )
    stop_timeout_s: float = Field(
        2.0, gt=0, le=60, description="deadline of a stop request (also while the controller is unreachable)"
    )
    reconnect_initial_s: float = Field(0.25, gt=0, le=60)
    reconnect_max_s: float = Field(5.0, gt=0, le=600)
    acceleration_m_s2: float = Field(1.2, gt=0, le=10)
    joint_acceleration_rad_s2: float = Field(1.4, gt=0, le=40)
    position_tolerance_mm: float = Field(0.2, gt=0, le=10, description="a move has arrived within this")
    joint_tolerance_rad: float = Field(0.002, gt=0, le=0.1)
    tool_turn_speed_deg_s: float = Field(
        180.0, gt=0, le=360, description="the most a linear move turns the tool, deg/s (a UR5e's joints: 180); "
        "below it moveL turns at 4 x its speed in rad/s (drivers/robot/ur_movel.py): a belt run plans with it")
    tracking_tolerance_mm: float = Field(
        1.0, gt=0, le=10, description="a move while tracking the belt has arrived within this of the moving target")
    watchdog_min_frequency_hz: float = Field(
        10.0, ge=1.0, le=50.0,
        description="the controller's RTDE watchdog, armed for every move: with no update from us for "
        "1/f s (the service died) the controller stops the arm",
    )

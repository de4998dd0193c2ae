"""The child processes of the ``ur_rtde`` adapter (``drivers/robot/ur_rtde.py``).

Kept free of numpy/scipy/pydantic imports so that a worker starts in well under a second: a
reconnect after an outage is one new process.
"""

from __future__ import annotations

import contextlib
import os
import time
from multiprocessing.connection import Connection
from typing import Any

# shared-memory layout of the newest sample
_SEQ, _HOST_T, _ROBOT_T, _POSE, _Q, _QD, _TCP_SPEED = 0, 1, 2, 3, 9, 15, 21
_ROBOT_MODE, _SAFETY_MODE, _RUNTIME, _STATUS_BITS, _DIN, _DOUT, _HEARTBEAT, _CONNECTED = range(27, 35)
_SHM_SIZE = 36


# -- child processes --------------------------------------------------------------------------------


def _quiet_stdout() -> None:
    """ur_rtde prints to stdout; keep it off the caller's stdout (CLI JSON) by sending it to stderr."""
    with contextlib.suppress(OSError):
        os.dup2(2, 1)


def _state_worker(host: str, frequency_hz: float, shm: Any, error: Any, stop: Any) -> None:
    _quiet_stdout()
    try:
        import rtde_receive

        receiver = rtde_receive.RTDEReceiveInterface(host, frequency_hz)
    except Exception as exc:  # ur_rtde raises RuntimeError / boost errors of every kind
        error.value = f"cannot connect RTDE to {host}:30004: {exc}".encode()[:255]
        return
    period = 1.0 / frequency_hz
    last_ts = -1.0
    while not stop.is_set():
        try:
            if not receiver.isConnected():
                error.value = f"RTDE connection to {host} lost".encode()[:255]
                return
            ts = receiver.getTimestamp()
            now = time.time()
            if ts != last_ts:
                last_ts = ts
                values = [
                    ts,
                    *receiver.getActualTCPPose(),
                    *receiver.getActualQ(),
                    *receiver.getActualQd(),
                    *receiver.getActualTCPSpeed(),
                    receiver.getRobotMode(),
                    receiver.getSafetyMode(),
                    receiver.getRuntimeState(),
                    receiver.getRobotStatus(),
                    receiver.getActualDigitalInputBits(),
                    receiver.getActualDigitalOutputBits(),
                ]
                with shm.get_lock():
                    shm[_HOST_T] = now
                    shm[_ROBOT_T : _DOUT + 1] = values
                    shm[_SEQ] += 1
                    shm[_CONNECTED] = 1.0
            shm[_HEARTBEAT] = now
        except Exception as exc:
            error.value = f"RTDE receive failed: {exc}".encode()[:255]
            return
        time.sleep(period / 2)
    with contextlib.suppress(Exception):
        receiver.disconnect()


def _control_worker(host: str, frequency_hz: float, conn: Connection) -> None:
    _quiet_stdout()
    import dashboard_client

    dash: Any = None
    ctrl: Any = None
    io: Any = None

    def control() -> Any:
        nonlocal ctrl, io
        if ctrl is None or not ctrl.isConnected():
            import rtde_control

            ctrl = rtde_control.RTDEControlInterface(host, frequency_hz)
        elif not ctrl.isProgramRunning():
            ctrl.reuploadScript()
            time.sleep(0.3)
        return ctrl

    def io_interface() -> Any:
        nonlocal io
        if io is None or not io.isConnected():
            import rtde_io

            io = rtde_io.RTDEIOInterface(host)
        return io

    def dashboard() -> Any:
        nonlocal dash
        if dash is None or not dash.isConnected():
            dash = dashboard_client.DashboardClient(host)
            dash.connect()
        return dash

    while True:
        try:
            op, args = conn.recv()
        except (EOFError, OSError):
            break
        try:
            result: Any = None
            if op == "moveL":
                result = control().moveL(*args)
            elif op == "moveJ":
                result = control().moveJ(*args)
            elif op == "stopL":
                if ctrl is not None:
                    result = ctrl.stopL(*args)
            elif op == "stopJ":
                if ctrl is not None:
                    result = ctrl.stopJ(*args)
            elif op == "fk":
                result = list(control().getForwardKinematics(*args))
            elif op == "digital_out":
                result = io_interface().setStandardDigitalOut(*args)
            elif op == "dashboard":
                method = getattr(dashboard(), args[0])
                result = method()
            elif op == "close":
                conn.send(("ok", None))
                break
            else:
                raise ValueError(f"unknown control request {op!r}")
            conn.send(("ok", result))
        except Exception as exc:
            conn.send(("error", f"{type(exc).__name__}: {exc}"))
    for obj in (ctrl, io, dash):
        if obj is not None:
            with contextlib.suppress(Exception):
                obj.disconnect()

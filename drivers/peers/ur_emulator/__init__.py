"""A Universal Robots controller emulator that the real ``ur_rtde`` clients connect to.

It speaks the controller's side of three protocols on one host, one module each:

- **RTDE** (port 30004, ``rtde.py``): recipes, start/pause and data packages at up to 500 Hz
  (an e-Series controller, version 5.11);
- **dashboard server** (port 29999, ``dashboard.py``): the line protocol (``robotmode``,
  ``power on``, ``brake release``, ``unlock protective stop``, ``PolyscopeVersion``, ...);
- **script server** (port 30003, also 30001/30002, ``script.py``): receives URScript and plays
  ``ur_rtde``'s control script's register handshake.

The simulated arm (``arm.py``) is a UR5e (its published DH parameters): ``moveL`` moves the TCP
in a straight line at the commanded speed (m/s), ``moveJ`` moves the joints at the commanded
speed (rad/s), ``stopL``/``stopJ`` stop, a protective stop (``triggerProtectiveStop``) halts it
until the dashboard's ``unlock protective stop``, and ``setWatchdog`` arms the control script's
RTDE watchdog: input updates that stop for 1/f s stop the program and the arm (``script.py``).
Standard digital outputs are wired back to the standard digital inputs (output *i* drives input
*i*), so IO can be tested through the real protocol.

We write our own here because no UR simulator runs without Docker (URSim); the protocol details
follow ``ur_rtde``'s sources (``rtde.cpp``, ``rtde_control_interface.cpp``, ``dashboard_client.cpp``).
``ur_rtde`` holds the GIL during its calls, so run the emulator in its own process
(:func:`run`, or ``cellctl sim ur``, or ``python -m drivers.peers.ur_emulator``).

``ur_rtde`` always connects to the fixed ports (30004, 29999, 30003); callers that start
emulators in tests serialise on :func:`fixed_port_lock`.
"""

from drivers.peers.ur_emulator.arm import HOME_Q, forward_kinematics, inverse_kinematics
from drivers.peers.ur_emulator.dashboard import dashboard_reply
from drivers.peers.ur_emulator.emulator import (
    DASHBOARD_PORT,
    PORT_LOCK_PATH,
    RTDE_PORT,
    SCRIPT_PORTS,
    UrEmulator,
    fixed_port_lock,
    main,
    run,
)

__all__ = [
    "DASHBOARD_PORT", "HOME_Q", "PORT_LOCK_PATH", "RTDE_PORT", "SCRIPT_PORTS", "UrEmulator", "dashboard_reply",
    "fixed_port_lock", "forward_kinematics", "inverse_kinematics", "main", "run",
]

"""Protocol peers: the far ends the drivers talk to, runnable on 127.0.0.1 for tests and demos.

Each one speaks a real protocol so the adapter under test runs unchanged: ``ur_emulator`` (a UR
controller for the real ``ur_rtde`` clients), ``modbus_robot`` (a pymodbus server playing a PLC
and its robot), ``serial_light`` and ``robotiq_gripper`` (serial devices on a pty). They are not
adapters: the simulated adapters (``kind: sim``) sit beside the adapters they stand for.
"""

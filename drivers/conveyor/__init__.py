"""Conveyor adapters: a belt's encoder count and speed (``kind: sim_conveyor``; docs/conveyor.md)."""

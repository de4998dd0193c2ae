"""cellctl: the robot work-cell controller service (config, cell, routines, pick, store, API, CLI)."""

__version__ = "0.1.0"

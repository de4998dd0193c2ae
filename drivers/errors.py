"""The drivers' typed errors, split by phase (python-can style): every one is a ``DriverError``.

Messages say what failed and what to do about it. ``DeviceUnavailable`` is also a
``ConnectionError`` and ``DeviceTimeout`` a ``TimeoutError``, so generic callers can catch those.
"""

from __future__ import annotations


class DriverError(Exception):
    """Root of every driver error. Messages say what failed and what to do about it."""


class DeviceUnavailable(DriverError, ConnectionError):
    """The device cannot be reached (not connected, unplugged, peer gone)."""


class DeviceInitError(DriverError):
    """The device was reached but could not be set up (bad setting, missing feature or library)."""


class DeviceOperationError(DriverError):
    """A command to a working device failed (malformed reply, rejected command)."""


class DeviceTimeout(DriverError, TimeoutError):
    """The device did not answer in time."""


class DriverInputError(DriverError, ValueError):
    """Bad input handed to a driver (a recording folder, a scene file, a render or imaging setting, a
    pose no joint solution reaches): the caller's to fix, not a device fault (the REST API answers 422)."""


class MotionRejected(DriverError, ValueError):
    """A commanded motion was refused before it was sent (envelope, speed, not allowed)."""

"""A library error's hint in a front end's words: the library names what is wrong and which of its
inputs are at fault; the command line and the REST API each name those inputs their own way
(``--plane-z-mm`` on the command line, ``plane_z_mm`` in a ``POST /map`` body).
"""

from __future__ import annotations

from collections.abc import Mapping

from calibration.measure import MappingError


def mapping_message(exc: MappingError, names: Mapping[str, str]) -> str:
    """``exc``'s message with what to do about its inputs, each called by its front end's ``names``
    (an input missing from ``names`` keeps the library's name)."""
    if not exc.inputs:
        return str(exc)
    said = " and ".join(names.get(i, i) for i in exc.inputs)
    if exc.need == "give":
        return f"{exc}: give {said}"
    if exc.need == "leave out":
        return f"{exc}; leave {said} out"
    return f"{exc}; check {said}"

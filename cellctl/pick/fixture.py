"""A fixture found by vision in a pick picture: the same frame as the parts, the one conversion.

A fixture (a recipe's ``located`` place: a tray or nest whose pockets are the slots) is searched in
the frame :func:`cellctl.pick.candidate.locate` grabbed for the parts, and its best match is mapped
like a part's (``cellctl.pick.pose.part_pose``): the reference point onto the fixture's top face
(``plane_z_mm``), a second point along the match's angle for its taught x axis. That is
``T_base_fixture`` (4x4, metres); the place's slots are fixed in its frame (production's
``LocatedPlace.T_slot_in_fixture``). Production asks for it through ``locate(..., fixture=place)``,
so a cycle enters this package once, for the picture.
"""

from __future__ import annotations

from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from cellctl.mapping import ActiveMapping
from cellctl.pick.model import PartModel
from cellctl.pick.pose import part_pose
from vision.recognize import recognize
from vision.types import SearchParams

FIXTURE_TIMEOUT_S = 5.0
"""The fixture's search time budget, s."""


class FixtureSpec(Protocol):
    """What a fixture search needs (production's ``LocatedPlace`` has it)."""

    @property
    def model(self) -> Any: ...  # a taught model document (pydantic: ``model_dump``)
    @property
    def plane_z_mm(self) -> float: ...
    @property
    def min_score(self) -> float: ...
    @property
    def roi(self) -> tuple[float, float, float, float] | None: ...


def fixture_model(spec: FixtureSpec) -> PartModel:
    return PartModel.from_dict(spec.model.model_dump(mode="json"), "the located place's fixture model")


def locate_fixture(spec: FixtureSpec, pixels: NDArray[Any], mapping: ActiveMapping,
                   T_capture: NDArray[np.float64] | None) -> tuple[NDArray[np.float64] | None, dict[str, Any]]:
    """The fixture's pose in the base frame (4x4, metres; None when not found) and what was found
    (``score``, ``u_px``, ``v_px``, ``angle_deg``, or ``reason``). ``T_capture``: the tool's pose at the
    grab for a camera on the arm (hand-eye), else None."""
    search = SearchParams(min_score=spec.min_score, max_count=1, roi=spec.roi, timeout_s=FIXTURE_TIMEOUT_S)
    found = recognize([fixture_model(spec)], pixels, search)
    if not found.matches:
        return None, {"reason": f"the place's fixture was not found (min_score {spec.min_score:g}): "
                                f"{found.reason() or 'no match'}"}
    m = found.matches[0]
    T = part_pose(mapping, m.u_px, m.v_px, m.angle_deg, spec.plane_z_mm, T_capture, with_uncertainty=False).T_base_part
    return T, {"score": float(m.score), "u_px": float(m.u_px), "v_px": float(m.v_px), "angle_deg": float(m.angle_deg)}

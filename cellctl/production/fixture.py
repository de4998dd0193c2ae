"""A place found by vision (a recipe's ``located`` place): the fixture in a cycle's picture.

The fixture's model is searched in the same frame as the parts; its best match is mapped like a
part's, by the one conversion for parts and fixtures (``cellctl.pick.pose.part_pose``): the
reference point onto the fixture's top face (``plane_z_mm``), a second point along the match's
angle for its taught x axis. That is ``T_base_fixture``; the place's slots are fixed in its frame
(``LocatedPlace.T_slot_in_fixture``).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from cellctl.mapping import ActiveMapping
from cellctl.pick.model import PartModel
from cellctl.pick.pose import part_pose
from cellctl.production.config import LocatedPlace
from vision.recognize import recognize
from vision.types import SearchParams

FIXTURE_TIMEOUT_S = 5.0
"""The fixture's search time budget, s."""


def fixture_model(place: LocatedPlace) -> PartModel:
    return PartModel.from_dict(place.model.model_dump(mode="json"), "the located place's fixture model")


def locate_fixture(place: LocatedPlace, pixels: NDArray[Any], mapping: ActiveMapping,
                   T_capture: NDArray[np.float64] | None) -> tuple[NDArray[np.float64] | None, dict[str, Any]]:
    """The fixture's pose in the base frame (4x4, metres; None when not found) and what was found
    (``score``, ``u_px``, ``v_px``, ``angle_deg``, or ``reason``)."""
    search = SearchParams(min_score=place.min_score, max_count=1, roi=place.roi, timeout_s=FIXTURE_TIMEOUT_S)
    found = recognize([fixture_model(place)], pixels, search)
    if not found.matches:
        return None, {"reason": f"the place's fixture was not found (min_score {place.min_score:g}): "
                                f"{found.reason() or 'no match'}"}
    m = found.matches[0]
    T = part_pose(mapping, m.u_px, m.v_px, m.angle_deg, place.plane_z_mm, T_capture, with_uncertainty=False).T_base_part
    return T, {"score": float(m.score), "u_px": float(m.u_px), "v_px": float(m.v_px), "angle_deg": float(m.angle_deg)}


def slots_in_base(place: LocatedPlace, T_base_fixture: NDArray[np.float64]) -> list[NDArray[np.float64]]:
    """Every slot's pose in the base frame for the fixture found at ``T_base_fixture``."""
    return [T_base_fixture @ place.T_slot_in_fixture(k) for k in range(place.slot_count())]

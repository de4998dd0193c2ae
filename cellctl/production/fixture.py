"""A place found by vision (a recipe's ``located`` place): the slots of the fixture a picture found.

The fixture itself is found in the cycle's picture by ``cellctl.pick`` (``locate(..., fixture=place)``,
``cellctl.pick.fixture``), in the same visit as the parts; ``T_base_fixture`` comes back on the
``Located``. The place's slots are fixed in the fixture's frame (``LocatedPlace.T_slot_in_fixture``).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from cellctl.production.config import LocatedPlace


def slots_in_base(place: LocatedPlace, T_base_fixture: NDArray[np.float64]) -> list[NDArray[np.float64]]:
    """Every slot's pose in the base frame for the fixture found at ``T_base_fixture``."""
    return [T_base_fixture @ place.T_slot_in_fixture(k) for k in range(place.slot_count())]

"""The slot a run's part goes to: chosen, claimed before the part is carried there, settled at the end.

Exactly once (docs/production.md): the slot is claimed in the store (``Store.claim_slot``, the
counter moves past it in the same transaction) before the part is carried there, and confirmed by
the cycle's ``placed`` record once the gripper has let it go; a run that ends in between (a Stop,
the service shutting down, an error) leaves the slot ``in_doubt``: no run places there until an
engineer confirms it (``settle``).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

import numpy as np

from cellctl.pick.recipe import PickError, Recipe
from cellctl.production.config import LocatedPlace
from cellctl.production.records import clean
from cellctl.store import Store

log = logging.getLogger(__name__)


class SlotClaims:
    """One run's slot counter and the claim of the part being carried (None: none, or confirmed)."""

    def __init__(self, store: Store, recipe_id: int, run_id: int) -> None:
        self.store, self.recipe_id, self.run_id = store, recipe_id, run_id
        self.next_slot = store.free_slot(recipe_id)
        self.claim: int | None = None
        """The slot claimed for the part carried now (None: none claimed, or confirmed)."""
        self.released = False
        """The gripper has let the claimed slot's part go (the release returned)."""

    def target(self, r: Recipe, T_base_fixture: np.ndarray | None, fixture: dict[str, Any] | None
               ) -> tuple[int, int | None, np.ndarray]:
        """The next free slot, the pattern's slot count (None: a fixed place) and the slot's pose (4x4, m,
        base frame). Checked before the pick: a full pattern or a missing fixture ends the run with the part
        where it lies, not in the gripper (``PickError``; a missing fixture: ``FixtureNotFound``)."""
        slot = self.next_slot = self.store.free_slot(self.recipe_id)  # past every slot claimed or in doubt
        if r.place is None:
            raise PickError(f"recipe {self.recipe_id} has no place section: a production run needs one "
                            "(docs/production.md)")
        n_slots = r.place.slot_count()
        if n_slots is not None and slot >= n_slots:
            raise PickError(f"the place pattern is full (slot {slot} of {n_slots}): empty it and reset the slot "
                            "(PUT /production/slot)")
        if isinstance(r.place, LocatedPlace):
            if T_base_fixture is None:
                raise FixtureNotFound((fixture or {}).get("reason") or "the place's fixture was not found")
            return slot, n_slots, T_base_fixture @ r.place.T_slot_in_fixture(slot)
        return slot, n_slots, r.place.T_slot(slot)

    def take(self, slot: int, n_slots: int | None, cycle_n: int, poses: dict[str, Any]) -> None:
        """Claim ``slot`` (stored, the counter past it) before the part goes there. A fixed place has no
        slots: what takes the part away is not the cell's, and nothing is claimed."""
        if n_slots is None:
            return
        self.store.claim_slot(self.recipe_id, slot, self.run_id, cycle_n, clean(poses))
        self.claim, self.released = slot, False
        self.next_slot = slot + 1

    def resolve(self) -> int | None:
        """The claim the cycle's ``placed`` record confirms (one transaction); no claim after it."""
        claimed, self.claim = self.claim, None
        return claimed

    def settle(self, why: str, phase: str, held: Callable[[], bool | None], pick_pose: Any,
               placed: Callable[[int, str], None]) -> dict[str, Any]:
        """The run ends with a slot claimed: placed when the gripper let the part go (``placed(slot,
        detail)`` records it), else in doubt. Written at once (not queued): the next run must see it.
        The cycle record's slot fields."""
        slot, self.claim = self.claim, None
        if slot is None:
            return {}
        if self.released:  # the record resolves the claim (one transaction, queued before the 'stopped' one)
            placed(slot, f"placed; the run then stopped while leaving the slot ({why})")
            return {}
        detail = {"phase": phase, "why": why, "held": held(), "pick_pose": pick_pose}
        try:
            self.store.slot_in_doubt(self.recipe_id, slot, self.run_id, clean(detail))
        except Exception:  # noqa: BLE001 - the claim stays 'claimed': in doubt at the next start all the same
            log.exception("production run %s: storing slot %s as in doubt failed", self.run_id, slot)
        return {"slot": slot, "slot_state": "in_doubt", "phase": phase}


class FixtureNotFound(PickError):
    """A located place's fixture was not in the picture: the part is left where it lies."""

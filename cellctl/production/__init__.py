"""Production pick-and-place: the run that empties a pick area into a place pattern, cycle after cycle.

- ``gripper``: open, close, check the grip, release (Robotiq 2F / sim gripper, vacuum, parallel);
- ``place``: place poses of a picked part (``place_poses``: the slot, the pick's grasp);
- the runs, the cycle records, the slot counter and the slot claims are tables of the store
  (``cellctl.store.production``: ``Store.claim_slot`` ... exactly once); ``interrupted``: runs the
  service did not end, ended at the next start;
- ``records``: a run's counters, cycle times and cycle records; ``frames``: failed cycles' frames on disk;
- ``choice``: which part a cycle picks (retries, skips, unreachable parts);
- ``vision``: a cycle's picture (the pick's candidates, ``cellctl.pick.locate``), the next one taken
  while the robot places;
- ``slots``: the slot a part goes to, claimed before the carry and settled at the run's end;
- ``run``: the run's thread and the still area's cycle (one run per robot); ``run_control``: the run's
  control from other threads (pause, resume, stop, abort; ``public``, ``snapshot``) and its states
  between cycles and at the end (``status``: the settings, status and state names); ``conveyor_run``
  (its threads and cycle), ``belt_meeting`` (meeting a part) and ``belt``: a run from a moving belt;
  ``manager``: the runs of a service.

The public names are listed in ``__all__`` (imported on first use).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from drivers.lazy import lazy_getattr

if TYPE_CHECKING:
    from cellctl.production.frames import FailureFrames
    from cellctl.production.gripper import GripCheck, Gripper
    from cellctl.production.manager import GripperHolding, NoRun, ProductionManager, ProductionRunning
    from cellctl.production.place import place_poses
    from cellctl.production.records import to_csv
    from cellctl.production.run import ProductionRun, RunSettings, RunStatus
    from cellctl.production.vision import Picture, Prefetch, VisionWorker, take_picture

__all__ = [
    "FailureFrames",
    "GripCheck",
    "Gripper",
    "GripperHolding",
    "NoRun",
    "Picture",
    "Prefetch",
    "ProductionManager",
    "ProductionRun",
    "ProductionRunning",
    "RunSettings",
    "RunStatus",
    "VisionWorker",
    "place_poses",
    "take_picture",
    "to_csv",
]

__getattr__ = lazy_getattr(__name__, {
    "GripperHolding": "cellctl.production.manager",
    "NoRun": "cellctl.production.manager",
    "ProductionManager": "cellctl.production.manager",
    "ProductionRunning": "cellctl.production.manager",
    "ProductionRun": "cellctl.production.run",
    "RunSettings": "cellctl.production.run",
    "RunStatus": "cellctl.production.run",
    "GripCheck": "cellctl.production.gripper",
    "Gripper": "cellctl.production.gripper",
    "place_poses": "cellctl.production.place",
    "Picture": "cellctl.production.vision",
    "Prefetch": "cellctl.production.vision",
    "VisionWorker": "cellctl.production.vision",
    "take_picture": "cellctl.production.vision",
    "FailureFrames": "cellctl.production.frames",
    "to_csv": "cellctl.production.records",
})
"""Public names imported on first use (PEP 562): importing the package stays cheap and free of cycles."""

"""Production pick-and-place: the run that empties a pick area into a place pattern, cycle after cycle.

- ``gripper``: open, close, check the grip, release (Robotiq 2F / sim gripper, vacuum, parallel);
- ``place``: place poses from the recipe's place section, the part's yaw and the gripper's symmetry;
- the runs, the cycle records, the slot counter and the slot claims are tables of the store
  (``cellctl.store.production``: ``Store.claim_slot`` ... exactly once); ``interrupted``: runs the
  service did not end, ended at the next start;
- ``records``: a run's counters, cycle times and cycle records; ``frames``: failed cycles' frames on disk;
- ``choice``: which part a cycle picks (retries, skips, unreachable parts);
- ``vision``: a cycle's picture (and the next one, taken while the robot places);
- ``run``: the run's cycles and state machine (one per robot); ``manager``: the runs of a service.
"""

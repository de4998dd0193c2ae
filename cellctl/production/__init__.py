"""Production pick-and-place: the run that empties a pick area into a place pattern, cycle after cycle.

- ``gripper``: open, close, check the grip, release (Robotiq 2F / sim gripper, vacuum, parallel);
- ``place``: place poses from the recipe's place section, the part's yaw and the gripper's symmetry;
- the next free slot, the runs and the cycle records are stored (``cellctl.store.production``);
- ``records``: a run's counters, cycle times and cycle records; ``frames``: failed cycles' frames on disk;
- ``choice``: which part a cycle picks (retries, skips, unreachable parts);
- ``vision``: a cycle's picture (and the next one, taken while the robot places);
- ``run``: the run's cycles and state machine (one per robot); ``manager``: the runs of a service.
"""

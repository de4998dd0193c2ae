"""Production pick-and-place: the run that empties a pick area into a place pattern, cycle after cycle.

- ``gripper``: open, close, check the grip, release (Robotiq 2F / sim gripper, vacuum, parallel);
- ``place``: place poses from the recipe's place section, the part's yaw and the gripper's symmetry;
- ``slots``, ``records``: the next free slot and the cycle records (stored: ``cellctl.store.production``);
- ``counters``: a run's counters and cycle times;
- ``cycle``: one cycle's steps; ``run``: the run's state machine (one per robot).
"""

"""The virtual cell: the scene, the world it renders and the arm's kinematics (a product, not a mock).

The adapters that live in it sit beside the adapters they stand for (``drivers/camera/sim.py``,
``drivers/robot/sim.py``); the protocol peers the tests talk to are in ``drivers/peers/``.
"""

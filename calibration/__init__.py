"""Camera and hand-eye calibration: pure geometry on arrays and files (no driver, no service).

At the top, what every job shares: ``geometry``, ``camera_model``, ``targets``, ``observations``
(the ``Detection``), ``verdict``. Each job is a package with its public names in its ``__init__``:
``detect``, ``intrinsics``, ``pose``, ``handeye``, ``npoint``, ``measure``, ``report``, ``io`` and
``synthetic`` (data with truth). The map: docs/packages.md.
"""

"""Test and bench support, out of the product's import path (the product never imports it):
a served ``cellctl`` process (``served``), a served cell with its PLC servers (``served_plc``),
the app in-process (``app``), the CLI in-process (``cli``), a served production cell
(``production_cell``), rendered pick scenes with known part poses (``pick_scenes``). The
benchmarks import it too (``python bench/x.py`` from the repository root puts the root on
``sys.path``)."""

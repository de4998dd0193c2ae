"""``python -m calibration.synthetic scara|tcp FOLDER``: write a virtual data set with its truth.

The data sets are the ones docs/calibrations-beyond-6dof.md walks through (``write_example``).
"""

from __future__ import annotations

import argparse
import sys

from calibration.synthetic.special import write_example


def main(argv: list[str] | None = None) -> int:
    """Write the data set named on the command line; print each file written."""
    ap = argparse.ArgumentParser(prog="python -m calibration.synthetic",
                                 description="Write a virtual SCARA hand-eye or tool-centre data set.")
    ap.add_argument("kind", choices=["scara", "tcp"])
    ap.add_argument("folder")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    for name, path in write_example(a.kind, a.folder, a.seed).items():
        print(f"{name}: {path}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Writer process for the kill test: saves large calibrations (and activates some) in a loop.

``python kill_writer.py URL CELL_ID START`` prints ``begin N`` before save number N and
``saved N ID VERSION SHA256`` once ``save_calibration`` has returned (the transaction committed),
``active ID`` after an activation returned; everything flushed at once. It runs until killed.
"""

from __future__ import annotations

import sys
from typing import Any

import numpy as np

BLOB_BYTES = 1_000_000
"""Random bytes per payload, stored as hex: about 2 MB of JSON per calibration, cheap to make, so
that the writer spends its time inside the database write where the kills should land."""


def payload(n: int) -> tuple[dict[str, Any], dict[str, Any]]:
    """The result and inputs of save number ``n``: large, and regenerable from ``n`` alone."""
    rng = np.random.default_rng(n)
    result = {"n": n, "K": [[1000.0 + n, 0.0, 320.0], [0.0, 1000.0, 240.0], [0.0, 0.0, 1.0]],
              "dist": rng.normal(size=5).tolist()}
    inputs = {"n": n, "observations_px": (rng.normal(size=(2000, 2)) * 500.0).tolist(),
              "robot_poses": rng.normal(size=(30, 6)).tolist(), "images_hex": rng.bytes(BLOB_BYTES).hex()}
    return result, inputs


def main() -> None:
    from cellctl.store import Store

    url, cell_id, start = sys.argv[1], sys.argv[2], int(sys.argv[3])
    store = Store(url, cell_id)
    n = start
    while True:
        result, inputs = payload(n)
        print(f"begin {n}", flush=True)
        rec = store.save_calibration("handeye", "cam0", "ur0", result, inputs, "kill-writer", note=f"n={n}")
        print(f"saved {n} {rec.id} {rec.version} {rec.sha256}", flush=True)
        if n % 2 == 0:
            store.activate(rec.id, "kill-writer")
            print(f"active {rec.id}", flush=True)
        n += 1


if __name__ == "__main__":
    main()

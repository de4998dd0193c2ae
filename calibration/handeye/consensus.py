"""Stations far off the consensus of a hand-eye solution (ours).

The screw-invariant check (``checks.find_outlier_stations``) needs no solution, but it sees only the
part of a pose error that changes a relative motion's angle or its shift along the axis, and it is
relative to the median station: on an arm with millimetre, pose-dependent error a station whose
recorded pose is 12 mm / 1.9° off scores only 5x the median and passes its 8x threshold.

This check uses the solution. Each station's target pose is predicted from its recorded robot pose
through ``X``, ``Z`` and the chosen error model's systematic correction (no per-station correction:
the consensus of the others), and compared with what its image shows: rotation (deg), target
position (mm) and the pixel RMS of its target points. A station is **off the consensus** when its
pixel miss exceeds ``CONSENSUS_FACTOR`` times the median station's and its rotation or position
miss exceeds the floors (``CONSENSUS_FLOOR_DEG`` / ``CONSENSUS_FLOOR_MM``: below them no pose file
error is worth a warning). It is **dropped** only when held-out prediction agrees: a calibration
without it misses it by more than ``CONSENSUS_FACTOR`` times the median held-out miss (the others
cannot predict it either; a station that only looks off because it pulls the solution is kept).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Final

import numpy as np

from calibration.handeye.frames import transform_error_deg_mm
from calibration.handeye.joint import JointProblem, LMResult
from calibration.handeye.model import Station

CONSENSUS_FACTOR: Final = 5.0
"""Times the median station's miss (px). Good stations on the kinematic-error arm and the real ETH
arm reach 2-3x the median; a 12 mm / 1.9° station 10-50x."""
CONSENSUS_FLOOR_DEG: Final = 0.3
CONSENSUS_FLOOR_MM: Final = 3.0


def consensus_misses(job: JointProblem, res: LMResult, stations: Sequence[Station]) -> list[dict[str, Any]]:
    """Per station: how far the solution's prediction from its recorded robot pose (systematic
    correction applied, no per-station correction) is from what its image shows —
    ``rot_deg``, ``trans_mm`` (target origin, camera frame) and ``rms_px`` (its target points)."""
    out = []
    for s in stations:
        Cp, uv = job.predict(res.x, s.G, s.obj)
        rot, trans = transform_error_deg_mm(Cp, s.C)
        e = uv - s.uv
        out.append({"image": s.image, "rot_deg": rot, "trans_mm": trans,
                    "rms_px": float(np.sqrt(np.mean(np.sum(e * e, axis=1))))})
    return out


def off_consensus(misses: Sequence[dict[str, Any]]) -> list[int]:
    """Indices of the stations off the consensus (module docstring)."""
    if len(misses) < 4:
        return []
    px = np.array([m["rms_px"] for m in misses])
    med = float(np.median(px))
    return [k for k, m in enumerate(misses)
            if m["rms_px"] > CONSENSUS_FACTOR * med
            and (m["rot_deg"] > CONSENSUS_FLOOR_DEG or m["trans_mm"] > CONSENSUS_FLOOR_MM)]


def confirmed_by_held_out(flagged: Sequence[int], loo_per_pose: Sequence[dict[str, Any]]) -> list[int]:
    """The flagged stations that a calibration without them also misses by more than
    ``CONSENSUS_FACTOR`` times the median held-out miss (px)."""
    if not flagged or len(loo_per_pose) < 4:
        return []
    px = np.array([p["rms_px"] for p in loo_per_pose])
    med = float(np.median(px))
    return [k for k in flagged if px[k] > CONSENSUS_FACTOR * med]

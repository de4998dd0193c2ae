"""Find the tool's feature in a fixed camera's image: a saturated spot in a dark ring.

The tool-centre step of jog-to-mark turns the tool and needs, at each angle, the pixel of one
feature the tool carries (a lit LED or a retro-reflective dot on a dark gripper body). Such a
spot is the one place in view that saturates the sensor, and it is surrounded by dark:

1. pixels at or above ``saturation_dn`` are grouped into regions (OpenCV's
   ``connectedComponentsWithStats``); regions touching the image border are skipped;
2. each region must be ringed by dark: the median grey of a band around it is at most
   ``ring_max_fraction`` of the spot's level (a bright plate or a specular edge is not);
3. exactly one region must pass (none or two is an error that says so);
4. the centre is the grey-weighted centroid over the spot and its edge, each pixel weighted by
   ``(grey - ring) / (spot - ring)`` clipped to [0, 1] — the pixel's area coverage by the spot
   when the ring is uniform — so it is sub-pixel and unbiased by thresholding.

Pixels in, pixels out (``(u, v)``, the centre of the top-left pixel is (0, 0)). Our own small
module on OpenCV's primitives; ``vision.blob`` needs a taught model, this needs none.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final

import cv2
import numpy as np
from numpy.typing import NDArray

from calibration import CalibrationError

SATURATION_DN: Final = 250.0
RING_MAX_FRACTION: Final = 0.5
MIN_AREA_PX: Final = 4


class SpotNotFound(CalibrationError):
    """No single spot (saturated and ringed by dark) in the image; the message says what was seen."""


@dataclass(frozen=True)
class Spot:
    u_px: float
    v_px: float
    radius_px: float
    """Radius of a disk of the spot's weighted area."""
    ring_dn: float
    """Median grey of the dark band around the spot."""


def find_spot(image: NDArray[np.generic], saturation_dn: float = SATURATION_DN,
              ring_max_fraction: float = RING_MAX_FRACTION) -> Spot:
    """The one saturated spot ringed by dark in a grey image (see the module docstring)."""
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    if img.ndim != 2 or img.size == 0:
        raise SpotNotFound(f"the image must be a grey or BGR picture, not of shape {np.shape(image)}")
    grey = img.astype(np.float64)
    h, w = grey.shape
    binary = (grey >= saturation_dn).astype(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(binary, connectivity=8)
    spots: list[Spot] = []
    unringed = 0
    for k in range(1, n):
        x, y, bw, bh, area = (int(v) for v in stats[k])
        if area < MIN_AREA_PX or x == 0 or y == 0 or x + bw >= w or y + bh >= h:
            continue
        r0 = 0.5 * max(bw, bh)
        spot = _refine(grey, labels == k, x + 0.5 * (bw - 1), y + 0.5 * (bh - 1), r0, ring_max_fraction)
        if spot is None:
            unringed += 1
        else:
            spots.append(spot)
    if not spots:
        why = (f"{unringed} saturated region(s), none ringed by dark" if unringed else
               f"no region at or above {saturation_dn:g} DN of at least {MIN_AREA_PX} px away from the border")
        raise SpotNotFound(f"the tool's spot is not seen: {why}; bring the feature into view (lit, not cut by "
                           "the border) or lower the exposure so nothing else saturates")
    if len(spots) > 1:
        where = ", ".join(f"({s.u_px:.0f}, {s.v_px:.0f})" for s in spots[:5])
        raise SpotNotFound(f"{len(spots)} spots ringed by dark at {where}: expected one; cover or dim the others")
    return spots[0]


def _refine(grey: NDArray[np.float64], region: NDArray[np.bool_], uc: float, vc: float, r0: float,
            ring_max_fraction: float) -> Spot | None:
    h, w = grey.shape
    r_in, r_band = r0 + 2.0, r0 + 4.0
    x0, x1 = max(int(uc - r_band) - 1, 0), min(int(uc + r_band) + 2, w)
    y0, y1 = max(int(vc - r_band) - 1, 0), min(int(vc + r_band) + 2, h)
    yy, xx = np.mgrid[y0:y1, x0:x1]
    d = np.hypot(xx - uc, yy - vc)
    win = grey[y0:y1, x0:x1]
    band = win[(d > r_in) & (d <= r_band)]
    spot_dn = float(np.median(grey[region]))
    if band.size == 0:
        return None
    ring = float(np.median(band))
    if ring > ring_max_fraction * spot_dn or spot_dn - ring <= 0:
        return None
    wgt = np.clip((win - ring) / (spot_dn - ring), 0.0, 1.0)
    wgt[d > r_in] = 0.0
    total = float(wgt.sum())
    if total <= 0:
        return None
    u = float((wgt * xx).sum() / total)
    v = float((wgt * yy).sum() / total)
    return Spot(u, v, float(np.sqrt(total / np.pi)), ring)

"""Detected target points of one image: the contract between detection and the solvers.

Pixels are ``(u, v)``, (0, 0) the centre of the top-left pixel. For circle marks ``uv`` is the
image of each mark's *centre* (perspective bias corrected as well as the detector could without
a calibrated camera) and ``uv_ellipse`` the raw fitted-ellipse centre, which solvers that know
the camera use with ``calibration.conic.circle_centre_bias_px`` inside their loop.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray


@dataclass
class Detection:
    """The points of one target found in one image (or why none were)."""

    image: str
    found: bool
    ids: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    uv: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 2)))
    uv_ellipse: NDArray[np.float64] | None = None
    reason: str = ""
    image_size: tuple[int, int] = (0, 0)
    """(width, height) of the image in pixels."""
    quality: dict[str, float] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        """The ``cellctl detect`` JSON of one image (shared/INTERFACES.md §4)."""
        points = []
        for k, i in enumerate(self.ids):
            p: dict[str, Any] = {"id": int(i), "u_px": float(self.uv[k, 0]), "v_px": float(self.uv[k, 1])}
            if self.uv_ellipse is not None:
                p["u_ellipse_px"] = float(self.uv_ellipse[k, 0])
                p["v_ellipse_px"] = float(self.uv_ellipse[k, 1])
            points.append(p)
        out: dict[str, Any] = {"image": self.image, "found": self.found, "points": points}
        if self.reason:
            out["reason"] = self.reason
        if self.image_size != (0, 0):
            out["width"], out["height"] = self.image_size
        if self.quality:
            out["quality"] = self.quality
        return out

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> Detection:
        pts = d.get("points", [])
        ids = np.array([p["id"] for p in pts], dtype=np.int64)
        uv = np.array([[p["u_px"], p["v_px"]] for p in pts], dtype=np.float64).reshape(-1, 2)
        ell = None
        if pts and "u_ellipse_px" in pts[0]:
            ell = np.array([[p["u_ellipse_px"], p["v_ellipse_px"]] for p in pts], dtype=np.float64)
        return cls(image=d["image"], found=bool(d["found"]), ids=ids, uv=uv, uv_ellipse=ell,
                   reason=d.get("reason", ""), image_size=(int(d.get("width", 0)), int(d.get("height", 0))),
                   quality=dict(d.get("quality", {})))

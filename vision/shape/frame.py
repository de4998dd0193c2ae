"""Which point of the part a match reports: moving it onto a measured point of the part.

A model's search works from its ROI's centre (``teach``), wherever the part lies in that box: for a
round part (a screw head) the point a cell wants is the part's centre, which an ROI drawn by hand
misses by a pixel or two. ``recentred`` sets ``ShapeModel.origin``: every match then reports that point
(``u_px, v_px``, moved with the match's turn), while the search and its fits stay exactly as taught (a
search's discrete grid is laid about the ROI centre; moving it changes which near-threshold
candidates survive). ``part_centre`` gives the origin from a point measured in each teach view
(several views: their mean in the part's frame, so one view's error in that measure is averaged
with the others'); ``origin_at`` and ``match_at_origin`` carry a search's pose of the ROI centre to
the origin (``search.find`` reports every match so).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from vision.errors import TeachError
from vision.image import F64
from vision.shape.model import ShapeModel
from vision.types import Match

Pose4 = tuple[float, float, float, float]


def recentred(model: ShapeModel, dx_px: float, dy_px: float) -> ShapeModel:
    """``model`` reporting the point ``(dx_px, dy_px)`` from its ROI centre (level-0 pixels of the teach
    image, x right, y down, the part as taught): the same edges, patch and search."""
    if not (math.isfinite(dx_px) and math.isfinite(dy_px)):
        raise TeachError(f"the reported point's offset ({dx_px!r}, {dy_px!r}) px must be finite")
    return ShapeModel(model.levels, model.params, model.roi, model.image_size, model.patch, model.view_tau,
                      (float(dx_px), float(dy_px)), model.colour)


def part_centre(poses: list[Pose4], centres: list[tuple[float, float]]) -> tuple[float, float]:
    """The mean, in the part's frame (level-0 pixels from the ROI centre, unturned), of the points
    ``centres[k]`` (image pixels) measured in teach views whose model poses (of the ROI centre) are
    ``poses[k]`` (x, y px, theta rad CCW on screen, scale)."""
    if len(poses) != len(centres) or not poses:
        raise TeachError(f"give one measured centre per teach view ({len(poses)} views, {len(centres)} centres)")
    out: list[F64] = []
    for (x, y, th, sc), (cx, cy) in zip(poses, centres, strict=True):
        c, s = math.cos(th), math.sin(th)
        R = np.array([[c, s], [-s, c]])  # model -> image (CCW on screen), as ShapeModel.contour
        out.append(R.T @ (np.array([cx - x, cy - y]) / sc))
    m = np.mean(out, axis=0)
    return float(m[0]), float(m[1])


def origin_at(origin: tuple[float, float], u: float, v: float, angle_deg: float, scale: float, mirrored: bool
              ) -> tuple[float, float]:
    """Where the model's ``origin`` (``ShapeModel.origin``) lies for a pose of its ROI centre at (u, v)."""
    ox = -origin[0] if mirrored else origin[0]
    a = math.radians(angle_deg)
    c, s = math.cos(a), math.sin(a)
    return u + scale * (c * ox + s * origin[1]), v + scale * (-s * ox + c * origin[1])


def match_at_origin(origin: tuple[float, float], mt: Match) -> Match:
    """``mt`` reported at the model's origin: the point moved with the match's turn and scale, and its
    1-sigma widened by the turn's 1-sigma times the origin's distance from the ROI centre (the two are
    nearly independent where the origin is the part's centre)."""
    u, v = origin_at(origin, mt.u_px, mt.v_px, mt.angle_deg, mt.scale, mt.mirrored)
    arm = mt.scale * math.hypot(*origin) * math.radians(mt.sigma_angle_deg)
    return replace(mt, u_px=u, v_px=v, sigma_px=math.hypot(mt.sigma_px, arm) if math.isfinite(arm) else mt.sigma_px)

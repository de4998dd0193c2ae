"""Shape models: edge points with gradient directions on every pyramid level, and their file form.

A model holds, per level of an image pyramid (``cv2.pyrDown``: level-``l`` pixel ``x`` lies at
level-0 ``2**l * x``), sub-pixel edge points relative to the reference point (the ROI centre, in
level pixels), their unit normals and the indices of the points the discrete search uses on that
level. Normals keep their sign (dark to bright), so the search can hold edges to their polarity.
``teaching.teach`` makes a model from a teach image's ROI (which edges, how many, where).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from vision.errors import TeachError
from vision.image import F64
from vision.shape.colour import COLOUR_MODES, ColourMix
from vision.shape.patch import TeachPatch, patch_from_dict, patch_to_dict

GRAD_PER_CONTRAST = 0.25  # peak gradient (grey/px) of a blurred step of unit contrast, roughly
CHAIN_MAX_TURN_DEG = 40.0
"""Two neighbouring edge pixels belong to one chain when their normals differ by less than this
(a contour rounded by the smoothing turns by well under it per pixel; texture does not)."""


@dataclass(frozen=True)
class TeachParams:
    """How the model was taught (stored in the model file)."""

    min_contrast: float = 12.0
    """Minimum grey-value step of an edge (teach and find)."""
    num_levels: int = 0
    """Pyramid levels (0 = automatic from the ROI size)."""
    edge_sigma_px: float = 1.0
    """Gaussian smoothing before the level-0 gradients."""
    auto_contrast: bool = True
    """Choose the model's edges by contrast relative to the ROI's strongest edges (HALCON's ``auto``):
    edges weaker than ``teaching.AUTO_CONTRAST_FRACTION`` of the ROI's 90th-percentile edge are texture, not
    the part's outline. ``min_contrast`` stays the floor, and the contrast asked of image edges at find."""
    min_component_px: int = 0
    """Least length (level-0 pixels) of a connected model edge; shorter ones (texture, specks) are
    dropped. 0: automatic (a tenth of the ROI's smaller side, at least 6 px)."""
    colour: str = "auto"
    """Which channel of a colour teach image the model is made of (``vision.shape.colour``): ``"auto"``
    (the default: the chroma where its edges are strong enough, else grey), ``"grey"`` (the grey value, as
    before session 16's default) or ``"chroma"`` (the colour edges, the background's shading left out). A
    grey image is always its grey value. (A model file without ``colour`` was taught grey.)"""

    def __post_init__(self) -> None:
        if not (math.isfinite(self.min_contrast) and 1.0 <= self.min_contrast <= 255.0):
            raise TeachError(f"min_contrast {self.min_contrast!r} must be 1..255 grey levels")
        if not 0 <= self.num_levels <= 8:
            raise TeachError(f"num_levels {self.num_levels} must be 0 (automatic) .. 8")
        if not (math.isfinite(self.edge_sigma_px) and 0.0 <= self.edge_sigma_px <= 5.0):
            raise TeachError(f"edge_sigma_px {self.edge_sigma_px!r} must be 0..5 px")
        if self.min_component_px < 0:
            raise TeachError(f"min_component_px {self.min_component_px} must be >= 0 (0: automatic)")
        if self.colour not in COLOUR_MODES:
            raise TeachError(f"colour {self.colour!r} must be one of {', '.join(COLOUR_MODES)}")

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"min_contrast": self.min_contrast, "num_levels": self.num_levels,
                               "edge_sigma_px": self.edge_sigma_px, "auto_contrast": self.auto_contrast,
                               "min_component_px": self.min_component_px}
        if self.colour != "grey":  # (a grey model's file as before)
            out["colour"] = self.colour
        return out

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TeachParams:
        # files taught before auto contrast keep their edges as they were chosen then
        return cls(float(d.get("min_contrast", 12.0)), int(d.get("num_levels", 0)),
                   float(d.get("edge_sigma_px", 1.0)), bool(d.get("auto_contrast", False)),
                   int(d.get("min_component_px", 0)), str(d.get("colour", "grey")))


@dataclass
class LevelModel:
    """Edge points of one pyramid level, relative to the reference point (level pixels)."""

    level: int
    points: F64
    """(N, 2) sub-pixel edge points."""
    normals: F64
    """(N, 2) unit gradient directions, dark to bright (the sign is the edge's polarity)."""
    features: NDArray[np.int64]
    """Indices of the points used for the discrete search on this level."""

    @property
    def radius(self) -> float:
        r = self.__dict__.get("_radius")
        if r is None:
            r = float(np.max(np.hypot(self.points[:, 0], self.points[:, 1])))
            self.__dict__["_radius"] = r
        return r

    @property
    def angle_step(self) -> float:
        """Angle step (rad) of the discrete tracking: the outermost point moves <= 1 px."""
        return 1.0 / max(self.radius, 2.0)

    def to_dict(self) -> dict[str, Any]:
        phi = np.degrees(np.arctan2(self.normals[:, 1], self.normals[:, 0]))
        return {"level": self.level,
                "points": [[round(float(x), 4), round(float(y), 4), round(float(a), 3)]
                           for (x, y), a in zip(self.points, phi, strict=True)],
                "features": [int(i) for i in self.features]}

    def mirrored(self) -> LevelModel:
        """The mirror image about the reference point's vertical axis (x -> -x)."""
        flip = np.array([-1.0, 1.0])
        return LevelModel(self.level, self.points * flip, self.normals * flip, self.features.copy())

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> LevelModel:
        arr = np.asarray(d["points"], dtype=np.float64).reshape(-1, 3)
        a = np.radians(arr[:, 2])
        feats = np.asarray(d["features"], dtype=np.int64)
        if len(arr) < 3 or len(feats) == 0 or feats.max() >= len(arr) or feats.min() < 0:
            raise TeachError(f"model level {d.get('level')} is corrupt (too few points or bad indices)")
        return cls(int(d["level"]), arr[:, :2].copy(), np.stack([np.cos(a), np.sin(a)], axis=1), feats)


@dataclass
class ShapeModel:
    """A taught shape model: one ``LevelModel`` per pyramid level (index = level)."""

    levels: list[LevelModel]
    params: TeachParams
    roi: tuple[float, float, float, float]
    image_size: tuple[int, int]
    patch: TeachPatch | None = None
    """The part's pixels in the teach image (``vision.shape.patch``): the final pose is finished on
    them; ``None`` (a model read from a file without them): the edge fit alone."""
    view_tau: tuple[float, float] = (0.0, 0.0)
    """(px, rad) the error a fit of the part has beyond its own covariance by how its look changes from
    view to view (a model taught from several views, ``multi.teach_many``: the spread of the edge fit
    against the patch fit over them, ``uncertainty.view_tau``); added to every match's 1-sigma. 0: one view."""
    origin: tuple[float, float] = (0.0, 0.0)
    """The point a match reports, relative to the ROI centre the search works from (level-0 pixels of
    the teach image, unturned; ``vision.shape.frame.recentred``): a measured centre of the part. The
    search does not depend on it (HALCON's ``set_shape_model_origin``)."""
    colour: ColourMix | None = None
    """The channel of a colour image the model was taught on and is searched in (``vision.shape.colour``);
    ``None``: the grey value."""

    @property
    def top_level(self) -> int:
        return len(self.levels) - 1

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"levels": [lv.to_dict() for lv in self.levels]}
        if self.patch is not None:
            out["patch"] = patch_to_dict(self.patch)
        if self.view_tau[0] > 0 or self.view_tau[1] > 0:
            out["view_sigma"] = {"px": round(self.view_tau[0], 4), "deg": round(math.degrees(self.view_tau[1]), 4)}
        if self.origin != (0.0, 0.0):
            out["origin_px"] = [round(self.origin[0], 4), round(self.origin[1], 4)]
        if self.colour is not None:
            out["colour"] = self.colour.to_dict()
        return out

    def view_cov(self) -> F64 | None:
        """``view_tau`` as a covariance of (x, y, theta) (px, rad), or ``None`` for a one-view model."""
        if self.view_tau[0] <= 0 and self.view_tau[1] <= 0:
            return None
        return np.diag([self.view_tau[0] ** 2, self.view_tau[0] ** 2, self.view_tau[1] ** 2])

    def contour(self, u_px: float, v_px: float, angle_deg: float, scale: float = 1.0,
                mirrored: bool = False) -> tuple[F64, F64]:
        """The level-0 model edge points and their unit tangents at a pose (a match's reported point), in
        image pixels."""
        lv = self.levels[0].mirrored() if mirrored else self.levels[0]
        a = math.radians(angle_deg)
        R = np.array([[math.cos(a), math.sin(a)], [-math.sin(a), math.cos(a)]])  # CCW on screen
        o = np.array([-self.origin[0] if mirrored else self.origin[0], self.origin[1]])
        pts = scale * (lv.points - o) @ R.T + np.array([u_px, v_px])
        n = lv.normals @ R.T
        return pts, np.stack([-n[:, 1], n[:, 0]], axis=1)

    def mirrored(self) -> ShapeModel:
        """The model of the part's mirror image (a flat part lying face down)."""
        return ShapeModel([lv.mirrored() for lv in self.levels], self.params, self.roi, self.image_size,
                          None if self.patch is None else self.patch.mirrored(), self.view_tau,
                          (-self.origin[0], self.origin[1]), self.colour)

    @classmethod
    def from_dict(cls, d: dict[str, Any], params: TeachParams, roi: tuple[float, float, float, float],
                  image_size: tuple[int, int]) -> ShapeModel:
        levels = [LevelModel.from_dict(x) for x in d["levels"]]
        patch = patch_from_dict(d["patch"], levels[0].points) if d.get("patch") is not None else None
        vs = d.get("view_sigma") or {}
        tau = (float(vs.get("px", 0.0)), math.radians(float(vs.get("deg", 0.0))))
        o = d.get("origin_px") or (0.0, 0.0)
        mix = ColourMix.from_dict(d["colour"]) if d.get("colour") is not None else None
        return cls(levels, params, roi, image_size, patch, tau, (float(o[0]), float(o[1])), mix)

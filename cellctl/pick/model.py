"""Part models: teach from an ROI, store as a versioned JSON file, find in images.

File layout (``format_version`` 1)::

    {"format_version": 1, "kind": "cellctl.pick.model", "name": "bracket", "mode": "shape",
     "teach": {"image": "teach.png", "image_size": [W, H], "roi": [U, V, W, H],
               "reference_px": [U + W/2, V + H/2], "params": {...}},
     "shape": {"levels": [{"level": 0, "points": [[x, y, normal_deg], ...], "features": [...]}, ...],
               "patch": {"origin_px": [x, y], "png_base64": "..."}}}
     (or "blob": {...} in blob mode; ``shape.patch``, the teach image's pixels of the part that finish
     a match's pose, is absent in files taught before it: those find with the edge fit alone;
     ``shape.view_sigma`` {"px", "deg"}, only in a model taught from several views: the error a fit has
     beyond its own 1-sigma by how the part's look changes between them, added to every match's;
     ``shape.origin_px`` [x, y], only where a centre of the part was measured at teach: the point a match
     reports, from the ROI centre, vision.shape.frame)

Point coordinates are relative to the reference point, in pixels of their pyramid level. A file
with a newer ``format_version`` than this code knows is refused with a clear message.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

import numpy as np
from numpy.typing import NDArray

from cellctl.errors import CellctlError
from vision import blob, shape
from vision.errors import SettingsError, VisionError
from vision.image import as_gray
from vision.types import FindResult, SearchParams

FORMAT_VERSION: Final[int] = 1
KIND: Final[str] = "cellctl.pick.model"
MODES: Final[tuple[str, ...]] = ("shape", "blob")

Roi = tuple[float, float, float, float]


class ModelFileError(CellctlError, VisionError):
    """A model file that cannot be used (unreadable, corrupt, or from a newer cellctl)."""


@dataclass
class PartModel:
    """A taught part: its mode's model plus where and how it was taught."""

    name: str
    mode: str
    roi: Roi
    image_size: tuple[int, int]
    teach_image: str | None
    shape: shape.ShapeModel | None = None
    blob: blob.BlobModel | None = None

    @property
    def reference_px(self) -> tuple[float, float]:
        """The teach image's point a match reports: the ROI centre, or a shape model's ``origin`` from it."""
        u, v, w, h = self.roi
        o = self.shape.origin if self.shape is not None else (0.0, 0.0)
        return (u + w / 2.0 + o[0], v + h / 2.0 + o[1])

    def find(self, image: NDArray[Any], search: SearchParams | None = None) -> FindResult:
        if self.shape is not None:
            return shape.find(self.shape, image, search)
        if self.blob is None:
            raise ModelFileError(f"part model {self.name} holds neither a shape nor a blob model")
        return blob.find(self.blob, image, search)

    def contour(self, u_px: float, v_px: float, angle_deg: float, scale: float = 1.0,
                mirrored: bool = False) -> NDArray[np.float64]:
        """Short edge segments ``(N, 2, 2)`` of the model drawn at a match's pose (image pixels);
        empty for a blob model, which has no edges."""
        if self.shape is None:
            return np.zeros((0, 2, 2))
        pts, tan = self.shape.contour(u_px, v_px, angle_deg, scale, mirrored)
        return np.stack([pts - 1.5 * tan, pts + 1.5 * tan], axis=1)

    def summary(self) -> dict[str, Any]:
        out: dict[str, Any] = {"name": self.name, "mode": self.mode, "roi": list(self.roi),
                               "reference_px": list(self.reference_px)}
        if self.shape is not None:
            out["levels"] = len(self.shape.levels)
            out["edge_points"] = int(len(self.shape.levels[0].points))
        elif self.blob is not None:
            out["area_px"] = self.blob.area_px
            out["polarity"] = self.blob.polarity
        return out

    def to_dict(self) -> dict[str, Any]:
        params: dict[str, Any] = {}
        body: dict[str, Any] = {}
        if self.shape is not None:
            params = self.shape.params.to_dict()
            body["shape"] = self.shape.to_dict()
        if self.blob is not None:
            params = self.blob.params.to_dict()
            body["blob"] = self.blob.to_dict()
        return {"format_version": FORMAT_VERSION, "kind": KIND, "name": self.name, "mode": self.mode,
                "teach": {"image": self.teach_image, "image_size": list(self.image_size),
                          "roi": list(self.roi), "reference_px": list(self.reference_px),
                          "params": params},
                **body}

    def save(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps(self.to_dict(), separators=(",", ":")) + "\n")

    @classmethod
    def from_dict(cls, d: dict[str, Any], source: str = "model") -> PartModel:
        if not isinstance(d, dict):
            raise ModelFileError(f"{source}: not a cellctl part model (expected a JSON object)")
        version = d.get("format_version")
        if not isinstance(version, int):
            raise ModelFileError(f"{source}: not a cellctl part model (no integer format_version)")
        if version > FORMAT_VERSION:
            raise ModelFileError(
                f"{source}: model format_version {version} is newer than this cellctl reads "
                f"({FORMAT_VERSION}); upgrade cellctl or teach the part again with this version")
        if d.get("kind", KIND) != KIND:
            raise ModelFileError(f"{source}: kind {d.get('kind')!r} is not a part model ({KIND})")
        mode = d.get("mode")
        if mode not in MODES:
            raise ModelFileError(f"{source}: unknown mode {mode!r} (expected one of {', '.join(MODES)})")
        try:
            teach = d["teach"]
            roi_l = [float(x) for x in teach["roi"]]
            roi: Roi = (roi_l[0], roi_l[1], roi_l[2], roi_l[3])
            size = (int(teach["image_size"][0]), int(teach["image_size"][1]))
            params = teach.get("params", {})
            m = cls(str(d.get("name", "part")), mode, roi, size, teach.get("image"))
            if mode == "shape":
                m.shape = shape.ShapeModel.from_dict(d["shape"], shape.TeachParams.from_dict(params), roi, size)
            else:
                m.blob = blob.BlobModel.from_dict(d["blob"], blob.BlobParams.from_dict(params))
        except (KeyError, TypeError, IndexError, ValueError) as exc:
            raise ModelFileError(f"{source}: the model is incomplete or corrupt ({exc})") from exc
        return m

    @classmethod
    def load(cls, path: str | Path) -> PartModel:
        p = Path(path)
        try:
            text = p.read_text()
        except OSError as exc:
            raise ModelFileError(f"cannot read model file {p}: {exc.strerror or exc}") from exc
        try:
            d = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ModelFileError(f"model file {p} is not valid JSON (line {exc.lineno}): "
                                 "teach the part again") from exc
        return cls.from_dict(d, str(p))


def check_roi(roi: Roi, image_size: tuple[int, int]) -> None:
    """Refuse an empty ROI or one reaching outside the image (``image_size`` = (W, H))."""
    u, v, w, h = roi
    if not all(math.isfinite(x) for x in roi):
        raise SettingsError(f"ROI {roi} is not finite")
    if w <= 0 or h <= 0:
        raise SettingsError(f"ROI {u:g},{v:g},{w:g},{h:g} is empty: width and height must be positive")
    W, H = image_size
    if u < 0 or v < 0 or u + w > W or v + h > H:
        raise SettingsError(f"ROI {u:g},{v:g},{w:g},{h:g} reaches outside the {W}x{H} image: "
                         f"keep 0 <= U, U+W <= {W} and 0 <= V, V+H <= {H}")


def teach(image: NDArray[Any], roi: Roi, *, mode: str = "shape", name: str = "part",
          teach_image: str | None = None, shape_params: shape.TeachParams | None = None,
          blob_params: blob.BlobParams | None = None) -> PartModel:
    """Teach a part model from the ROI ``(U, V, W, H)`` of ``image``; the ROI centre is the reference."""
    if mode not in MODES:
        raise SettingsError(f"unknown mode {mode!r}: use one of {', '.join(MODES)}")
    img = as_gray(np.asarray(image))
    size = (int(img.shape[1]), int(img.shape[0]))
    check_roi(roi, size)
    m = PartModel(name, mode, roi, size, teach_image)
    if mode == "shape":
        m.shape = shape.teach(img, roi, shape_params)
    else:
        m.blob = blob.teach(img, roi, blob_params)
    return m

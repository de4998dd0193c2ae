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
     reports, from the ROI centre, vision.shape.frame; ``shape.colour``, only in a model taught on a colour
     channel (``teach.params.colour`` ``chroma`` or ``auto``): the projection a colour image is searched in;
     ``"refine": "rim"``, only in a round part's model that measures its rim after each match: every match
     then reports the rim's centre and its 1-sigma, ``refine_rim``)

Point coordinates are relative to the reference point, in pixels of their pyramid level. A file
with a newer ``format_version`` than this code knows is refused with a clear message.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Final

import numpy as np
from numpy.typing import NDArray

from cellctl.errors import CellctlError
from vision import blob, shape
from vision.errors import SettingsError, TeachError, VisionError
from vision.image import as_gray
from vision.shape.colour import COLOUR_MODES, taught_mix
from vision.shape.model import GRAD_PER_CONTRAST
from vision.shape.rim import model_rim, rim_centre
from vision.types import FindResult, Match, SearchParams

FORMAT_VERSION: Final[int] = 1
KIND: Final[str] = "cellctl.pick.model"
MODES: Final[tuple[str, ...]] = ("shape", "blob")
REFINES: Final[tuple[str, ...]] = ("rim",)
"""What a match is finished with after the search (``PartModel.refine``): ``rim``, the round part's rim."""

Roi = tuple[float, float, float, float]


class ModelFileError(CellctlError, VisionError):
    """A model file that cannot be used (unreadable, corrupt, or from a newer cellctl)."""


class NotRoundPart(CellctlError, TeachError):
    """``refine: rim`` asked of a part whose model has no round outline to measure."""


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
    refine: str | None = None
    """``"rim"``: each match reports its rim's centre and 1-sigma (``refine_rim``); None: the match as found."""

    @property
    def reference_px(self) -> tuple[float, float]:
        """The teach image's point a match reports: the ROI centre, or a shape model's ``origin`` from it."""
        u, v, w, h = self.roi
        o = self.shape.origin if self.shape is not None else (0.0, 0.0)
        return (u + w / 2.0 + o[0], v + h / 2.0 + o[1])

    def find(self, image: NDArray[Any], search: SearchParams | None = None) -> FindResult:
        if self.shape is not None:
            res = shape.find(self.shape, image, search)
            if self.refine == "rim":
                for mt in res.matches:
                    refine_rim(self.shape, image, mt)
            return res
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
            out["colour"] = self.shape.params.colour
            out["channel"] = "chroma" if self.shape.colour is not None else "grey"
            if self.refine is not None:
                out["refine"] = self.refine
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
                **body, **({"refine": self.refine} if self.refine is not None else {})}

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
            refine = d.get("refine")
            if refine is not None and (refine not in REFINES or mode != "shape"):
                raise ModelFileError(f"{source}: refine {refine!r} is not one of {', '.join(REFINES)} on a shape "
                                     "model: teach the part again")
            m.refine = refine
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


def colour_mode(mode: str, asked: str | None) -> str:
    """The colour mode (vision.shape.colour) a teach uses: the one ``asked``, else a shape model's default
    (``TeachParams``': ``auto``, the chroma channel where the taught part is coloured against its background,
    else grey) and a blob model's (``grey``: a blob model is taught from one grey image)."""
    if asked is not None:
        return asked
    return shape.TeachParams().colour if mode == "shape" else "grey"


def takes_colour(images: Sequence[NDArray[Any]], rois: Sequence[Roi], params: shape.TeachParams) -> bool:
    """Whether a shape model taught with ``params`` from these views is made of a colour channel (so its
    images are read in colour; a grey model's as their grey values, as before colour models)."""
    for img, r in zip(images, rois, strict=True):
        check_roi(r, (int(img.shape[1]), int(img.shape[0])))
    return taught_mix(images, rois, params.colour, params.edge_sigma_px,
                      params.min_contrast * GRAD_PER_CONTRAST) is not None


def refine_rim(model: shape.ShapeModel, image: NDArray[Any], mt: Match) -> None:
    """Move the match ``mt`` (in place) to its rim's centre measured in ``image`` (vision.shape.rim), with
    the fit's 1-sigma per axis as ``sigma_px`` and ``refine`` ``"rim"``; where the image shows too little
    of the rim, ``mt`` keeps the model's prediction of it and ``refine`` says ``"rim_not_seen"``."""
    fit = rim_centre(model, image, mt)
    if fit is None:
        mt.refine = "rim_not_seen"
        return
    mt.u_px, mt.v_px, mt.sigma_px, mt.refine = fit.u_px, fit.v_px, fit.sigma_px, "rim"


def _with_rim(m: PartModel) -> None:
    """Make ``m`` report its rim's centre: the model's origin on the round outline's centre (so a match
    predicts it and the reference point is it), or ``NotRoundPart`` when the model has none."""
    if m.shape is None:
        raise NotRoundPart("refine 'rim' needs a shape model (mode shape): a blob model has no rim to measure")
    rim = model_rim(m.shape)
    if rim is None:
        raise NotRoundPart(f"refine 'rim' needs a round part: part {m.name!r}'s edges in the ROI lie on no circle "
                           "that goes round it (a screw head, a washer, a bore have one); teach it without refine, "
                           "or frame the round part alone")
    m.shape = replace(m.shape, origin=(rim[0], rim[1]))
    m.refine = "rim"


def teach(image: NDArray[Any], roi: Roi, *, mode: str = "shape", name: str = "part",
          teach_image: str | None = None, shape_params: shape.TeachParams | None = None,
          blob_params: blob.BlobParams | None = None,
          more_views: Sequence[tuple[NDArray[Any], Roi]] = (), refine: str | None = None) -> PartModel:
    """Teach a part model from the ROI ``(U, V, W, H)`` of ``image``; the ROI centre is the reference.

    ``more_views``: further (image, ROI) views of the same part (a shape model keeps the edges seen in all,
    vision.shape.multi). A colour image is taught as it is when ``shape_params.colour`` is ``chroma`` or
    ``auto`` (vision.shape.colour), else as its grey value (as before). ``refine="rim"``: a round part's
    matches report its rim's centre (``NotRoundPart`` when the part is not round)."""
    if mode not in MODES:
        raise SettingsError(f"unknown mode {mode!r}: use one of {', '.join(MODES)}")
    if refine is not None and refine not in REFINES:
        raise SettingsError(f"unknown refine {refine!r}: use one of {', '.join(REFINES)} (or none)")
    colour = shape_params.colour if shape_params is not None else colour_mode(mode, None)
    if colour not in COLOUR_MODES:
        raise SettingsError(f"unknown colour mode {colour!r}: use one of {', '.join(COLOUR_MODES)}")
    if mode != "shape" and (colour != "grey" or more_views or refine is not None):
        raise SettingsError("colour, several teach views and refine make a shape model: use mode 'shape' "
                            "(a blob model is taught from one grey image)")
    # a grey model is taught on the grey value exactly as before; a colour one on the image as it is
    img = as_gray(np.asarray(image)) if colour == "grey" else np.asarray(image)
    size = (int(img.shape[1]), int(img.shape[0]))
    check_roi(roi, size)
    m = PartModel(name, mode, roi, size, teach_image)
    if mode == "shape":
        if more_views:
            views = [(img, roi)] + [(as_gray(np.asarray(i)) if colour == "grey" else np.asarray(i), r)
                                    for i, r in more_views]
            for i, r in views[1:]:
                check_roi(r, (int(i.shape[1]), int(i.shape[0])))
            m.shape = shape.teach_many([i for i, _ in views], [r for _, r in views], shape_params)
        else:
            m.shape = shape.teach(img, roi, shape_params)
        if refine == "rim":
            _with_rim(m)
    else:
        m.blob = blob.teach(img, roi, blob_params)
    return m

"""The part-model file format (``cellctl.pick.model``, ``format_version`` 1) as a strict schema.

A recipe carries its part models as JSON (what ``POST /pick/teach`` and ``cellctl pick teach``
answer); this schema is what a ``models`` entry must look like before it is stored: the keys
``PartModel.to_dict`` writes, every number finite, of JSON number type and in its range (pixels
within +-1e5, angles within +-360 degrees, indices and sizes integers in range), so a 400-digit
number or a ``true`` where a float belongs is refused naming its place (``models.0.teach.roi.2``)
instead of reaching numpy. Keys are optional where older files lack them (the reader's defaults).
Units: pixels of the teach image (points: of their pyramid level, relative to the reference
point); angles in degrees.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, model_serializer, model_validator
from pydantic_core.core_schema import SerializerFunctionWrapHandler

from cellctl.pick.model import FORMAT_VERSION
from cellctl.strict_types import Bool, Count, Num

MAX_PX = 1e5
"""No image or ROI is 100 000 pixels across."""
MAX_IMAGE_SIDE_PX = 100_000
MAX_LEVELS = 16
MAX_POINTS = 200_000
"""Edge points of one level (a taught model has a few thousand)."""
MAX_PATCH_B64 = 64_000_000
"""The teach patch's PNG in base64 (a 4000 x 3000 grey patch is about 16 MB)."""

Px = Annotated[Num, Field(ge=-MAX_PX, le=MAX_PX)]
Deg = Annotated[Num, Field(ge=-360.0, le=360.0)]
Side = Annotated[Count, Field(ge=1, le=MAX_IMAGE_SIDE_PX)]
Index = Annotated[Count, Field(ge=0, le=MAX_POINTS)]


class _Part(BaseModel):
    """Forbids unknown keys; dumps only the keys it was given (a stored model stays as taught)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    @model_serializer(mode="wrap")
    def _given_keys_only(self, handler: SerializerFunctionWrapHandler) -> dict[str, Any]:
        out: dict[str, Any] = handler(self)
        return {k: v for k, v in out.items() if k in self.model_fields_set}


class TeachParamsDoc(_Part):
    """``teach.params``: the shape teach parameters (vision.shape.TeachParams) or the blob ones
    (vision.blob.BlobParams)."""

    min_contrast: Num | None = Field(None, ge=1, le=255)
    num_levels: Count | None = Field(None, ge=0, le=8)
    edge_sigma_px: Num | None = Field(None, ge=0, le=5)
    auto_contrast: Bool | None = None
    min_component_px: Count | None = Field(None, ge=0, le=MAX_IMAGE_SIDE_PX)
    colour: Literal["auto", "grey", "chroma"] | None = None
    threshold: Num | None = Field(None, ge=0, le=255)
    polarity: Literal["auto", "bright", "dark"] | None = None
    area_tolerance: Num | None = Field(None, ge=0, le=100)
    shape_tolerance: Num | None = Field(None, ge=0, le=100)


class TeachDoc(_Part):
    image: str | None = Field(None, max_length=4096)
    image_size: tuple[Side, Side]
    roi: tuple[Px, Px, Px, Px]
    reference_px: tuple[Px, Px] | None = None
    params: TeachParamsDoc = TeachParamsDoc()


class LevelDoc(_Part):
    level: Count = Field(ge=0, le=MAX_LEVELS)
    points: list[tuple[Px, Px, Deg]] = Field(min_length=3, max_length=MAX_POINTS,
                                             description="[x, y, normal_deg] relative to the reference point")
    features: list[Index] = Field(min_length=1, max_length=MAX_POINTS)


class PatchDoc(_Part):
    """``shape.patch``: the part's pixels in the teach image (vision.shape.patch), a grey PNG."""

    origin_px: tuple[Px, Px]
    png_base64: str = Field(min_length=4, max_length=MAX_PATCH_B64)


class ViewSigmaDoc(_Part):
    """``shape.view_sigma``: a model taught from several views, the error a fit has beyond its own 1-sigma
    by how the part's look changes between them (vision.shape.multi.spread); added to every match's."""

    px: Num = Field(ge=0, le=MAX_PX)
    deg: Num = Field(ge=0, le=180)


class ColourDoc(_Part):
    """``shape.colour``: the channel of a colour image the model was taught on and is searched in
    (vision.shape.colour): ``offset + weights_bgr . (B, G, R)``, the weights' absolute values summing to 1."""

    weights_bgr: tuple[Num, Num, Num] = Field(description="weights of B, G, R")
    offset: Num = Field(ge=-255, le=510)


class ShapeDoc(_Part):
    levels: list[LevelDoc] = Field(min_length=1, max_length=MAX_LEVELS)
    patch: PatchDoc | None = None
    view_sigma: ViewSigmaDoc | None = None
    origin_px: tuple[Px, Px] | None = None
    """The point a match reports, from the ROI centre (px, the part as taught; vision.shape.frame)."""
    colour: ColourDoc | None = None


class BlobDoc(_Part):
    polarity: Literal["bright", "dark"]
    threshold: Num = Field(ge=0, le=255)
    area_px: Num = Field(ge=0, le=MAX_PX * MAX_PX)
    elongation: Num = Field(ge=0, le=1e6)
    compactness: Num = Field(ge=0, le=100)
    angle_deg: Deg
    directed: Bool
    offset_px: tuple[Px, Px]


class PartModelDoc(_Part):
    """One part model as a recipe's ``models`` entry."""

    format_version: Count = Field(ge=1, le=FORMAT_VERSION)
    kind: Literal["cellctl.pick.model"] = "cellctl.pick.model"
    name: str = Field("part", max_length=256)
    mode: Literal["shape", "blob"]
    teach: TeachDoc
    shape: ShapeDoc | None = None
    blob: BlobDoc | None = None
    refine: Literal["rim"] | None = None
    """``rim``: a round part's matches report its rim's centre and 1-sigma (cellctl.pick.model); absent: as found."""

    @model_validator(mode="before")
    @classmethod
    def _known_version(cls, data: Any) -> Any:
        if isinstance(data, dict) and "preview" in data:
            # The teach answer's drawing aid (POST /pick/teach?preview=true) is not part of the model.
            data = {k: v for k, v in data.items() if k != "preview"}
        version = data.get("format_version") if isinstance(data, dict) else None
        if isinstance(version, int) and not isinstance(version, bool) and version > FORMAT_VERSION:
            raise ValueError(f"model format_version {version} is newer than this cellctl reads ({FORMAT_VERSION}); "
                             "upgrade cellctl or teach the part again with this version")
        return data

    @model_validator(mode="after")
    def _mode_has_its_model(self) -> PartModelDoc:
        if getattr(self, self.mode) is None:
            raise ValueError(f"a {self.mode} model needs its {self.mode!r} section (what teach wrote)")
        if self.refine is not None and self.mode != "shape":
            raise ValueError(f"refine {self.refine!r} needs a shape model (a {self.mode} model has no rim to measure)")
        return self

"""What a search is asked (``SearchParams``) and what it answers (``Match``, ``FindResult``).

Shared by the shape and blob matchers. Positions are pixels (centre of the top-left pixel =
``(0, 0)``); ``angle_deg`` is the rotation relative to the teach image, counter-clockwise on
screen (``cv2.getRotationMatrix2D`` sense), in (-180, 180].
"""

from __future__ import annotations

from dataclasses import dataclass, field

PERSPECTIVE_DEFAULT = True


@dataclass(frozen=True)
class SearchParams:
    """Bounds of one search."""

    min_score: float = 0.5
    max_count: int = 0
    """Most matches to return (0: all)."""
    angle_start_deg: float = -180.0
    angle_extent_deg: float = 360.0
    roi: tuple[float, float, float, float] | None = None
    """Search region ``(U, V, W, H)`` for the reference point; ``None``: the whole image."""
    timeout_s: float | None = None
    min_distance_px: float | None = None
    """Two matches closer than this are one (default: a third of the model's smaller size)."""
    max_overlap: float = 0.5
    """A match whose model rectangle overlaps a better one's by more than this fraction is dropped."""
    max_scale_dev: float = 0.1
    """The final fit may scale the model by up to this fraction (a slightly tilted view); 0: rigid."""
    perspective: bool = PERSPECTIVE_DEFAULT
    """Finish with a plane-homography fit (a tilted camera): the reference point and angle are then
    those of the part's plane seen in perspective."""


@dataclass
class Match:
    u_px: float
    v_px: float
    angle_deg: float
    score: float
    rms_px: float = float("nan")
    """RMS normal distance of the inlier model edge points after refinement."""
    scale: float = 1.0
    """Apparent size relative to the teach image (a tilted view), from the final fit."""

    def as_dict(self) -> dict[str, float]:
        return {"u_px": self.u_px, "v_px": self.v_px, "angle_deg": self.angle_deg, "score": self.score,
                "scale": self.scale}


@dataclass
class FindResult:
    matches: list[Match]
    timed_out: bool = False
    elapsed_s: float = 0.0
    stats: dict[str, float] = field(default_factory=dict)


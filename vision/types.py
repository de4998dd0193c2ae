"""What a search is asked (``SearchParams``) and what it answers (``Match``, ``FindResult``).

Shared by the shape and blob matchers. Positions are pixels (centre of the top-left pixel =
``(0, 0)``); ``angle_deg`` is the rotation relative to the teach image, counter-clockwise on
screen (``cv2.getRotationMatrix2D`` sense), in (-180, 180]. ``SearchParams`` checks itself when
it is made: settings that cannot work raise ``SettingsError`` naming the field and the fix.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Literal

from vision.errors import SettingsError

PERSPECTIVE_DEFAULT = True
POLARITIES = ("use_polarity", "ignore_global_polarity", "ignore_local_polarity")
Polarity = Literal["use_polarity", "ignore_global_polarity", "ignore_local_polarity"]
MIN_SCORE_FLOOR = 0.1
"""Below this a score no longer tells a part from texture: every edge pixel would be a candidate."""


def _finite(name: str, x: float) -> float:
    if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x):
        raise SettingsError(f"{name} must be a finite number, got {x!r}")
    return float(x)


@dataclass(frozen=True)
class SearchParams:
    """Bounds of one search (HALCON ``find_shape_model``'s parameters, in our words)."""

    min_score: float = 0.5
    """Least score of a match, in [0.1, 1]."""
    max_count: int | None = None
    """Most matches to return (``None``: all)."""
    angle_start_deg: float = -180.0
    angle_extent_deg: float = 360.0
    """Angles searched: ``angle_start_deg`` .. ``+ angle_extent_deg`` (0 < extent <= 360)."""
    roi: tuple[float, float, float, float] | None = None
    """Search region ``(U, V, W, H)`` for the reference point; ``None``: the whole image."""
    timeout_s: float | None = None
    """The search's own time budget (wall clock, s): it starts after the matcher's compiled loops are
    loaded (``shape.warm_up``), so a first search in a process has the same budget as the next ones."""
    min_distance_px: float | None = None
    """Two matches closer than this are one (default: a third of the model's smaller size)."""
    max_overlap: float = 0.5
    """A match whose model rectangle overlaps a better one's by more than this fraction is dropped."""
    max_scale_dev: float = 0.1
    """The final fit may scale the model by up to this fraction (a slightly tilted view); 0: rigid."""
    perspective: bool = PERSPECTIVE_DEFAULT
    """Finish with a plane-homography fit (a tilted camera): the reference point and angle are then
    those of the part's plane seen in perspective."""
    polarity: Polarity = "ignore_local_polarity"
    """``use_polarity``: edges must have the teach image's contrast direction; ``ignore_global_polarity``:
    or all of them reversed (an inverted image); ``ignore_local_polarity`` (the default): each edge
    either way — a part on a background that is darker on one side and brighter on the other, or
    pasted over by clutter, still scores (bench/results/pick.md: one fewer miss at 30 % occlusion than
    with ``ignore_global_polarity``, and the same on the real photographs)."""
    greediness: float = 0.9
    """0: safe, slower; 1: fast, may miss weak parts. A top-level candidate must reach
    ``(0.4 + greediness / 3) * min(min_score, 0.5)`` of the top-level response (0.7x at 0.9): lower
    lets weaker candidates through to the finer levels (HALCON's greediness in spirit; our exhaustive
    top level scores every position in full, so the knob is where candidates are cut)."""
    scale_min: float = 1.0
    scale_max: float = 1.0
    """Isotropic scale range searched (e.g. 0.9..1.1); 1..1 (the default): no scale search."""
    mirrored: bool = False
    """Also search the mirror image of the model (a flat part lying face down)."""
    min_visible: float = 0.5
    """A pose whose model lies more than this fraction inside the image is scored on its visible points."""
    min_surround: float = 0.2
    """How far the seen edges must enclose the part's centre, as a fraction of how far the whole model
    does (``vision.shape.verify``: 1 seen all round, about 0 for a half): at 0.2 a piece of the part
    (its half) is not answered as the part, a part up to about a third hidden is; 0 answers fragments
    down to a half, -1 switches the check off."""

    def __post_init__(self) -> None:
        ms = _finite("min_score", self.min_score)
        if not MIN_SCORE_FLOOR <= ms <= 1.0:
            raise SettingsError(f"min_score {self.min_score:g} is out of range: use {MIN_SCORE_FLOOR:g}..1 "
                                "(below it every textured patch would be a match)")
        if self.max_count is not None and (isinstance(self.max_count, bool) or not isinstance(self.max_count, int)
                                           or self.max_count < 1):
            raise SettingsError(f"max_count {self.max_count!r} asks for no match: give at least 1, or leave it "
                                "unset for all matches")
        _finite("angle_start_deg", self.angle_start_deg)
        ext = _finite("angle_extent_deg", self.angle_extent_deg)
        if not 0.0 < ext <= 360.0:
            raise SettingsError(f"angle_extent_deg {ext:g} is out of range: use 0 < extent <= 360 "
                                "(the range of angles searched, from angle_start_deg)")
        if self.roi is not None:
            if len(self.roi) != 4:
                raise SettingsError(f"roi must be (U, V, W, H), got {self.roi!r}")
            for k, x in zip("UVWH", self.roi, strict=True):
                _finite(f"roi {k}", x)
            if self.roi[2] <= 0 or self.roi[3] <= 0:
                raise SettingsError(f"roi {self.roi} is empty: width and height must be positive")
        if self.timeout_s is not None and not _finite("timeout_s", self.timeout_s) >= 0:
            raise SettingsError(f"timeout_s {self.timeout_s:g} must be >= 0 (0: answer at once; None: no limit)")
        if self.min_distance_px is not None and not _finite("min_distance_px", self.min_distance_px) >= 0:
            raise SettingsError(f"min_distance_px {self.min_distance_px:g} must be >= 0")
        if not 0.0 <= _finite("max_overlap", self.max_overlap) <= 1.0:
            raise SettingsError(f"max_overlap {self.max_overlap:g} must be a fraction 0..1")
        if not 0.0 <= _finite("max_scale_dev", self.max_scale_dev) <= 0.5:
            raise SettingsError(f"max_scale_dev {self.max_scale_dev:g} must be 0..0.5")
        if self.polarity not in POLARITIES:
            raise SettingsError(f"polarity {self.polarity!r} is unknown: use one of {', '.join(POLARITIES)}")
        if not 0.0 <= _finite("greediness", self.greediness) <= 1.0:
            raise SettingsError(f"greediness {self.greediness:g} must be 0..1 (0: safe, 1: fast)")
        lo, hi = _finite("scale_min", self.scale_min), _finite("scale_max", self.scale_max)
        if not 0.5 <= lo <= 1.0 <= hi <= 2.0:
            raise SettingsError(f"scale range {lo:g}..{hi:g} must lie in 0.5..2 and include 1 "
                                "(e.g. 0.9..1.1)")
        if not 0.1 <= _finite("min_visible", self.min_visible) <= 1.0:
            raise SettingsError(f"min_visible {self.min_visible:g} must be a fraction 0.1..1")
        if not -1.0 <= _finite("min_surround", self.min_surround) <= 1.0:
            raise SettingsError(f"min_surround {self.min_surround:g} must be -1..1 (1: seen all round the centre, "
                                "0: a half, -1: no check)")


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
    mirrored: bool = False
    """The mirror image of the model matched (the part lies face down)."""
    n_points: int = 0
    """Model points that agreed with an image edge at the final pose (direction and position)."""
    n_visible: int = 0
    """Model points inside the image at the final pose (the score is over these)."""
    sigma_angle_deg: float = float("nan")
    """1-sigma of ``angle_deg`` from the final fit (its residuals and geometry); NaN when unknown."""
    sigma_px: float = float("nan")
    """1-sigma of the reference point's position (px, the larger axis), from the same fit."""
    scores: dict[str, float] = field(default_factory=dict)
    """The verification's scores (``vision.shape.verify``): ``edge`` (= ``score``), ``coverage``,
    ``polarity``, ``contrast``, ``missing_features``, ``surround``, ``unclaimed``; a colour model's also
    ``interior`` (``vision.shape.colour.interior_verdict``)."""
    refine: str | None = None
    """What finished the point after the search (a part model's ``refine``): ``"rim"``, the round part's
    rim centre (``sigma_px`` is then the rim fit's, per axis); ``"rim_not_seen"``, asked but the image
    showed too little of the rim (the model's prediction of its centre); None: the match as found."""

    def as_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "u_px": self.u_px, "v_px": self.v_px, "angle_deg": self.angle_deg, "score": self.score,
            "scale": self.scale, "mirrored": self.mirrored, "n_points": self.n_points,
            "n_visible": self.n_visible, "sigma_angle_deg": finite_or_none(self.sigma_angle_deg),
            "sigma_px": finite_or_none(self.sigma_px), "scores": dict(self.scores)}
        if self.refine is not None:
            out["refine"] = self.refine
        return out


def finite_or_none(x: float) -> float | None:
    """``x``, or None when it is not finite (JSON has no NaN)."""
    return float(x) if math.isfinite(x) else None


@dataclass
class Rejected:
    """A candidate that reached ``min_score`` but failed the verification, with its scores and why."""

    u_px: float
    v_px: float
    angle_deg: float
    score: float
    mirrored: bool
    scores: dict[str, float]
    reason: str

    def as_dict(self) -> dict[str, Any]:
        return {"u_px": self.u_px, "v_px": self.v_px, "angle_deg": self.angle_deg, "score": self.score,
                "mirrored": self.mirrored, "scores": dict(self.scores), "reason": self.reason}


@dataclass
class Candidate:
    """The best pose a search saw, whether or not it passed ``min_score`` (to say why nothing was found)."""

    u_px: float
    v_px: float
    angle_deg: float
    score: float
    verdict: str | None = None
    """What the verification says of it at a lower ``min_score``: None (not checked), ``"pass"``, or
    why it would fail."""


@dataclass
class FindResult:
    matches: list[Match]
    timed_out: bool = False
    elapsed_s: float = 0.0
    stats: dict[str, float] = field(default_factory=dict)
    best_rejected: Candidate | None = None
    """The best candidate below ``min_score`` (``None`` if there was none)."""
    min_score: float = 0.5
    rejected: list[Rejected] = field(default_factory=list)
    """Candidates that reached ``min_score`` and failed the verification, best first."""

    def reason(self) -> str | None:
        """Why nothing was found, in one line (``None`` when something was)."""
        if self.matches:
            return None
        return no_match_reason(self.timed_out, self.best_rejected, self.min_score, self.rejected)


def no_match_reason(timed_out: bool, best: Candidate | None, min_score: float, rejected: list[Rejected]) -> str:
    """Why a search answered no match, in one line, with the setting that would change it."""
    if timed_out:
        return "the search timed out before any candidate was scored: raise timeout_s or narrow the search"
    if rejected:
        r = rejected[0]
        return (f"{len(rejected)} candidate(s) reached min_score but failed the verification; the best, "
                f"{r.score:.2f} at ({r.u_px:.1f}, {r.v_px:.1f}), angle {r.angle_deg:.1f} deg: {r.reason}")
    if best is None:
        return "no candidate: no part-like edges in the searched region"
    lower = max(math.floor(best.score * 100) / 100, MIN_SCORE_FLOOR)
    hint = ""
    if best.verdict == "pass":
        hint = f"; at min_score {lower:g} it would be answered (it passes the verification)"
    elif best.verdict:
        hint = f"; a lower min_score would not answer it either: {best.verdict}"
    return (f"best candidate scored {best.score:.2f} < min_score {min_score:g} "
            f"at ({best.u_px:.1f}, {best.v_px:.1f}), angle {best.angle_deg:.1f} deg{hint}")

"""Pure image search: shape-based and blob matching, recognition — arrays in, matches out.

- ``shape``: shape-based matching (edge-gradient model over a pyramid, any rotation, sub-pixel).
- ``blob``: threshold -> select regions by area/shape -> centre and orientation from moments.
- ``recognize``: several part models in one call, with the score margin to the runner-up.
- ``types``: ``SearchParams`` (what a search is asked), ``Match`` and ``FindResult`` (its answer).

Conventions: pixel centres at integers (the centre of the top-left pixel is ``(0, 0)``); the ROI
``(U, V, W, H)`` spans ``(U, V)``..``(U+W, V+H)`` and its centre is the reference point; a
match's ``angle_deg`` is the rotation relative to the teach image, counter-clockwise on screen
(``cv2.getRotationMatrix2D`` sense), in (-180, 180].

Imports numpy, OpenCV and scipy only: no ``cellctl``, no ``drivers``.
"""

from vision.errors import SettingsError, TeachError, VisionError
from vision.types import FindResult, Match, SearchParams

__all__ = ["FindResult", "Match", "SearchParams", "SettingsError", "TeachError", "VisionError"]

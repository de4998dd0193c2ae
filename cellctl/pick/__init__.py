"""Pick guidance, vision core: teach a part model, find it fast and sub-pixel accurate.

- ``model``: ``teach(image, roi, mode=...)`` -> ``PartModel`` (versioned JSON file), ``PartModel.find``.
- ``shape``: shape-based matching (edge-gradient model over a pyramid, any rotation, sub-pixel).
- ``blob``: threshold -> select regions by area/shape -> centre and orientation from moments.
- ``recognize``: several part models in one call, with the score margin to the runner-up.
- ``synth``: rendered scenes with known part poses (tests and ``bench/pick.py``).

Conventions (shared/INTERFACES.md §4): pixel centres at integers; the ROI ``(U, V, W, H)`` spans
``(U, V)``..``(U+W, V+H)`` and its centre is the reference point; a match's ``angle_deg`` is the
rotation relative to the teach image, counter-clockwise on screen (``cv2.getRotationMatrix2D``
sense), in (-180, 180].
"""

from cellctl.pick.model import FORMAT_VERSION, ModelFileError, PartModel, teach
from cellctl.pick.recognize import Recognition, RecognitionResult, recognize
from cellctl.pick.shape import FindResult, Match, SearchParams, TeachParams

__all__ = [
    "FORMAT_VERSION",
    "FindResult",
    "Match",
    "ModelFileError",
    "PartModel",
    "Recognition",
    "RecognitionResult",
    "SearchParams",
    "TeachParams",
    "recognize",
    "teach",
]

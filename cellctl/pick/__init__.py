"""Pick guidance: part models, recipes, the pick flow and the annotated frames.

- ``model``: ``teach(image, roi, mode=...)`` -> ``PartModel`` (versioned JSON file), ``PartModel.find``.
- ``recipe``, ``pose``, ``flow``: what to pick, match -> gripper pose, grab-locate-convert-check.
- ``frames``: the last frames, annotated with the matches.

The image search itself is the ``vision`` package (shape and blob matching, recognition).

Conventions (docs/cli.md): pixel centres at integers; the ROI ``(U, V, W, H)`` spans
``(U, V)``..``(U+W, V+H)`` and its centre is the reference point; a match's ``angle_deg`` is the
rotation relative to the teach image, counter-clockwise on screen (``cv2.getRotationMatrix2D``
sense), in (-180, 180].
"""

from cellctl.pick.model import FORMAT_VERSION, ModelFileError, PartModel, teach
from vision.recognize import Recognition, RecognitionResult, recognize
from vision.shape import TeachParams
from vision.types import FindResult, Match, SearchParams

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

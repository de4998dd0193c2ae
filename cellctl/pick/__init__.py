"""Pick guidance: part models, recipes, the pick flow and the annotated frames.

- ``model``: ``teach(image, roi, mode=...)`` -> ``PartModel`` (versioned JSON file), ``PartModel.find``.
- ``recipe``, ``pose``, ``flow``: what to pick, match -> gripper pose, grab-locate-convert-check.
- ``candidate``: the one path from a match to a pick: ``locate`` grabs, searches and returns typed
  ``PickCandidate``s (match, ``T_base_part`` and its sigma, grasp, reachable), computed once, for
  REST, the PLC and production alike; ``pose.part_pose`` turns any match (part or fixture) into
  ``T_base_part``, ``pose.fold_yaw`` is the one gripper-symmetry fold.
- ``frames``: the last frames, annotated with the matches.

The image search itself is the ``vision`` package (shape and blob matching, recognition).

Conventions (docs/cli.md): pixel centres at integers; the ROI ``(U, V, W, H)`` spans
``(U, V)``..``(U+W, V+H)`` and its centre is the reference point; a match's ``angle_deg`` is the
rotation relative to the teach image, counter-clockwise on screen (``cv2.getRotationMatrix2D``
sense), in (-180, 180].
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from drivers.lazy import lazy_getattr

if TYPE_CHECKING:
    from cellctl.pick.candidate import Located, PickCandidate, locate
    from cellctl.pick.flow import run_pick
    from cellctl.pick.model import FORMAT_VERSION, ModelFileError, PartModel, teach
    from cellctl.pick.pose import PartPose, fold_yaw, part_pose, pick_pose, pose_json
    from cellctl.pick.recipe import GripperSettings, PickError, Recipe, SearchSettings
    from vision.recognize import Recognition, RecognitionResult, recognize
    from vision.shape import TeachParams
    from vision.types import FindResult, Match, SearchParams

__all__ = [
    "FORMAT_VERSION",
    "FindResult",
    "GripperSettings",
    "Located",
    "Match",
    "ModelFileError",
    "PartModel",
    "PartPose",
    "PickCandidate",
    "PickError",
    "Recipe",
    "Recognition",
    "RecognitionResult",
    "SearchParams",
    "SearchSettings",
    "TeachParams",
    "fold_yaw",
    "locate",
    "part_pose",
    "pick_pose",
    "pose_json",
    "recognize",
    "run_pick",
    "teach",
]

__getattr__ = lazy_getattr(__name__, {
    "Located": "cellctl.pick.candidate",
    "PickCandidate": "cellctl.pick.candidate",
    "locate": "cellctl.pick.candidate",
    "run_pick": "cellctl.pick.flow",
    "FORMAT_VERSION": "cellctl.pick.model",
    "ModelFileError": "cellctl.pick.model",
    "PartModel": "cellctl.pick.model",
    "teach": "cellctl.pick.model",
    "PartPose": "cellctl.pick.pose",
    "fold_yaw": "cellctl.pick.pose",
    "part_pose": "cellctl.pick.pose",
    "pick_pose": "cellctl.pick.pose",
    "pose_json": "cellctl.pick.pose",
    "GripperSettings": "cellctl.pick.recipe",
    "PickError": "cellctl.pick.recipe",
    "Recipe": "cellctl.pick.recipe",
    "SearchSettings": "cellctl.pick.recipe",
    "Recognition": "vision.recognize",
    "RecognitionResult": "vision.recognize",
    "recognize": "vision.recognize",
    "TeachParams": "vision.shape",
    "FindResult": "vision.types",
    "Match": "vision.types",
    "SearchParams": "vision.types",
})
"""Public names imported on first use (PEP 562): importing the package runs none of its modules, so the
service root (``cellctl.services``, which uses this package's frames) and production (whose recipe
sections the recipe carries) import its modules without a cycle."""

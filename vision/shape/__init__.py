"""Shape-based matching: find a taught part at any rotation, to a fraction of a pixel and degree.

- ``model``: ``ShapeModel`` (edge points per pyramid level) and its file form.
- ``teaching``: ``teach(image, roi)`` -> ``ShapeModel``.
- ``responses``: quantized orientation response maps and the discrete pose search on them.
- ``search``: ``find(model, image, SearchParams)`` -> ``FindResult``, coarse to fine.
- ``refine``: least-squares sub-pixel refinement (similarity, then plane homography), with the
  pose's 1-sigma from the fit.
- ``verify``: the checks a refined match must pass before it is answered (scores per match).
- ``patch``: the taught patch (the part's pixels): finishes a match's pose, with an honest 1-sigma.
- ``multi``: ``teach_many(images, rois)``: a model from 2-5 images, keeping the edges seen in all.
- ``kernels``, ``fit_kernels``, ``search_kernels``: the compiled inner loops (numba): the edge measurements
  along the model normals, the refinement's Gauss-Newton loops, the discrete search's loops.
- ``warmup``: ``warm_up()`` loads the compiled loops before a timed search.
"""

from vision.shape.model import LevelModel, ShapeModel, TeachParams
from vision.shape.multi import teach_many
from vision.shape.search import find
from vision.shape.teaching import auto_levels, teach
from vision.shape.warmup import warm_up

__all__ = ["LevelModel", "ShapeModel", "TeachParams", "auto_levels", "find", "teach", "teach_many", "warm_up"]

"""Shape-based matching: find a taught part at any rotation, to a fraction of a pixel and degree.

- ``model``: ``teach(image, roi)`` -> ``ShapeModel`` (edge points per pyramid level).
- ``responses``: quantized orientation response maps and the discrete pose search on them.
- ``search``: ``find(model, image, SearchParams)`` -> ``FindResult``, coarse to fine.
- ``refine``: least-squares sub-pixel refinement (similarity, then plane homography), with the
  pose's 1-sigma from the fit.
- ``verify``: the checks a refined match must pass before it is answered (scores per match).
- ``kernels``: the compiled inner loops (numba); ``warm_up()`` loads them before a timed search.
"""

from vision.shape.kernels import warm_up
from vision.shape.model import LevelModel, ShapeModel, TeachParams, auto_levels, teach
from vision.shape.search import find

__all__ = ["LevelModel", "ShapeModel", "TeachParams", "auto_levels", "find", "teach", "warm_up"]

"""Loading the shape matcher's compiled loops (numba) once per process, before a timed search.

``warm_up`` loads (or, on a cold disk cache, compiles) every kernel of ``kernels``, ``fit_kernels``,
``search_kernels`` and ``score`` on tiny inputs, then runs one small real search so the first
timed search costs what the next ones cost. ``load_kernels`` is the loading alone (the test fork
server runs it before forking).
"""

from __future__ import annotations

import threading

import numpy as np

from vision.shape.fit_kernels import fit_stage_a, fit_stage_b, perspective_fit
from vision.shape.kernels import associate, magnitudes, percentile75, profile_centroids

_WARM = threading.Event()
_WARM_LOCK = threading.Lock()


def warm_up(image_size: tuple[int, int] | None = None) -> None:
    """Load (or compile) every kernel now, on tiny inputs, once per process: the first search then
    costs what the next ones cost. Loading the compiled code from numba's disk cache takes ~1 s;
    compiling it on a cold cache ~20 s. Thread-safe: a second caller waits for the first; later
    calls return at once. ``search.find`` calls it before its clock starts, so a search's
    ``timeout_s`` never pays for it. ``image_size`` ``(width, height)``: the images the searches
    will see (default 320x240); the warm-up's own small search runs on one that size, so the
    process's memory for such images is in place before the first timed search."""
    if _WARM.is_set():
        return
    with _WARM_LOCK:
        if not _WARM.is_set():
            load_kernels()
            _WARM.set()  # before the search below, which calls warm_up() itself
            _first_search(image_size or (320, 240))


def _first_search(image_size: tuple[int, int]) -> None:
    """One small real search (teach a drawn part, find it turned): loads whatever compiled loop a
    search reaches that ``load_kernels`` does not name, and pays the first call's one-off costs on the
    rest of the path (refinement, verification; first touches of image-sized buffers), so the next
    search costs what the hundredth does."""
    import cv2

    from vision.shape.search import find
    from vision.shape.teaching import teach

    w, h = max(int(image_size[0]), 320), max(int(image_size[1]), 240)
    img = np.full((h, w), 60, np.uint8)
    part = np.array([[110, 70], [210, 70], [210, 110], [160, 110], [160, 170], [110, 170]], np.int32)
    cv2.fillPoly(img, [part], 190)
    cv2.circle(img, (135, 95), 10, 60, -1)
    img = cv2.GaussianBlur(img, (5, 5), 0.8)
    model = teach(img, (90.0, 50.0, 140.0, 140.0))
    M = cv2.getRotationMatrix2D((160.0, 120.0), 25.0, 1.0)
    M[:, 2] += (7.3, -4.6)
    find(model, cv2.warpAffine(img, M, (w, h), borderValue=60))


def load_kernels() -> None:
    """Load (or compile) the matcher's compiled loops on tiny inputs: this package's kernels, the
    search's (``search_kernels.warm_up``) and the score's, and the score's noise reference per smoothing."""
    z2 = np.zeros((2, 2))
    associate(np.zeros((4, 4, 2), np.float32), z2, z2, 1, 1.0)
    profile_centroids(np.zeros((4, 4), np.float32), z2, z2, 1)
    fit_stage_a(np.zeros((4, 4, 2), np.float32), z2, z2, np.zeros(4), 1.0, 0.1, 1.0, 1, 1.0, 0.0, False, 1.0,
                0.0, 4.0, 4.0)
    perspective_fit(np.zeros((4, 4), np.float32), z2, z2, 0.0, 0.0, 0.0, 1.0, 1.0, 1)
    percentile75(magnitudes(np.zeros((4, 4, 2), np.float32), z2))
    fit_stage_b(np.zeros((4, 4), np.float32), z2, z2, 0.0, 0.0, 0.0, 1.0, 1.0, 0.1, 1.0, True, 1, 1.0, 0.0, 4.0,
                4.0, 1)
    from vision.shape import score, search_kernels
    search_kernels.warm_up()
    score.point_agreement(np.zeros((4, 4, 2), np.float32), z2, z2, 1.0, 1.5, 0.75, 0.5, 0.25)
    for sigma in (0.0, 1.0):  # the score's noise reference per smoothing, computed once per process
        score.find_threshold(np.zeros((8, 8), np.uint8), sigma, 3.0, 0.0)

"""The gradient magnitude's bits do not depend on where its buffers lie (``vision.image.magnitude``).

``cv2.magnitude``'s last bit depends on its output buffer's alignment (mod 64 bytes), which numpy's
allocator varies with the process's history: a model taught twice from the same image differed in its
last bits (with ``cv2.magnitude``, 2-4 different models from 4 teaches in one process, 10 runs of 10).
"""

from __future__ import annotations

import numpy as np

from tests.support import pick_scenes
from vision import shape
from vision.image import gradients, magnitude
from vision.shape import search_kernels


def _model_bits(m: shape.ShapeModel) -> bytes:
    return b"".join(a.tobytes() for lv in m.levels for a in (lv.points, lv.normals, lv.features))


def test_the_same_teach_gives_the_same_model_bits_wherever_its_buffers_land() -> None:
    part = pick_scenes.part_bracket()
    img, roi = pick_scenes.teach_scene(part, np.random.default_rng(1008), centre=(640.3, 480.6),
                                       style=pick_scenes.SceneStyle(size=(1280, 960), noise_sigma=1.5, clutter=0))
    held = []
    models = set()
    for k in range(8):
        held.append(np.empty(4096 + 16 * k, np.uint8))  # moves where the next buffers land, in 16-byte steps
        models.add(_model_bits(shape.teach(img, roi)))
    assert len(models) == 1


def test_the_response_planes_threshold_the_same_magnitude_to_the_bit() -> None:
    """``search_kernels.response_planes`` computes the magnitude in its loop: at thresholds on and one
    float32 step either side of the magnitudes themselves it keeps exactly the pixels ``magnitude``
    keeps (a float64 square root would differ at some of them)."""
    img = np.random.default_rng(0).integers(0, 255, (61, 83)).astype(np.uint8)
    gx, gy = gradients(img, 0.0)
    mag = magnitude(gx, gy)
    assert mag.dtype == np.float32
    np.testing.assert_allclose(mag, np.hypot(gx.astype(np.float64), gy.astype(np.float64)), rtol=1e-6)
    q = np.zeros(img.shape, np.uint8)
    table = np.array([[1, 0]], np.uint8)  # bin 0 responds 1, "no edge" 0
    out = np.empty((1,) + img.shape, np.uint8)
    for m in np.unique(mag)[::5]:
        for thr in (m, np.nextafter(m, np.float32(0)), np.nextafter(m, np.float32(np.inf))):
            search_kernels.response_planes(q, gx, gy, float(thr), table, out)
            np.testing.assert_array_equal(out[0] == 1, mag >= thr)

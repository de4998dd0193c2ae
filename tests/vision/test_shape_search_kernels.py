"""The matcher's compiled search loops against plain numpy versions of the same arithmetic.

The compiled loops (``vision.shape.search_kernels``, ``fit_kernels.perspective_fit``) replaced numpy
code for speed; these tests hold them to the numpy results on rendered scenes and random maps,
including the cases the fast paths treat apart: a part cut by the image border (bounds-checked
gathers), plateaus of equal scores, a partial angle range (no wrap-around) and a scaled model.
No timing here: speed lives in bench/pick.py.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from tests.support import pick_scenes as scenes
from vision import shape
from vision.image import CENTROID_HALF_WIDTH, pyramid
from vision.shape import fit_kernels, kernels, refine
from vision.shape import search_kernels as sk
from vision.shape.model import GRAD_PER_CONTRAST
from vision.shape.responses import BIN_W, N_BINS, response_maps, spread_max, track

SIZE = (640, 480)


@pytest.fixture(scope="module")
def scene() -> tuple[shape.ShapeModel, np.ndarray, list[scenes.Truth]]:
    part = scenes.part_bracket()
    style = scenes.SceneStyle(size=SIZE, noise_sigma=1.5, clutter=10)
    img, roi = scenes.teach_scene(part, np.random.default_rng(3), centre=(320.4, 240.7),
                                  style=scenes.SceneStyle(size=SIZE, noise_sigma=1.5, clutter=0))
    model = shape.teach(img, roi)
    # one part well inside, one cut by the left border, one by the bottom border
    inst = [scenes.Instance(part, 300.3, 200.6, 33.0), scenes.Instance(part, 25.0, 300.0, -70.0),
            scenes.Instance(part, 500.0, 470.0, 120.0)]
    test_img, truth = scenes.render(inst, style, np.random.default_rng(4))
    return model, test_img, truth


def _track_numpy(resp: np.ndarray, lm: shape.LevelModel, cx: np.ndarray, cy: np.ndarray, th: np.ndarray,
                 n_steps: int, reach: int, k_s: np.ndarray) -> tuple[np.ndarray, ...]:
    """The vectorised numpy tracking the compiled ``track_batch`` replaced (same contract)."""
    m = lm.points[lm.features]
    n = lm.normals[lm.features]
    nf = len(m)
    na = 2 * n_steps + 1
    thetas = th[:, None] + (np.arange(na) - n_steps)[None, :] * lm.angle_step
    c = (k_s[:, None] * np.cos(thetas))[..., None]
    s = (k_s[:, None] * np.sin(thetas))[..., None]
    dx = np.rint(c * m[:, 0] + s * m[:, 1]).astype(np.int64)
    dy = np.rint(-s * m[:, 0] + c * m[:, 1]).astype(np.int64)
    phi = np.arctan2(n[:, 1], n[:, 0]) - thetas[..., None]
    b = (np.floor(np.mod(phi, math.pi) / BIN_W).astype(np.int64)) % N_BINS
    _, h, w = resp.shape
    cx = np.clip(cx, 0, w - 1)
    cy = np.clip(cy, 0, h - 1)
    offs = np.arange(-reach, reach + 1)
    ox, oy = np.tile(offs, len(offs)), np.repeat(offs, len(offs))
    xs_ = cx[:, None, None, None] + ox[None, None, :, None] + dx[:, :, None, :]  # (C, A, P, F)
    ys_ = cy[:, None, None, None] + oy[None, None, :, None] + dy[:, :, None, :]
    inside = (xs_ >= 0) & (xs_ < w) & (ys_ >= 0) & (ys_ < h)
    bins = np.broadcast_to(b[:, :, None, :], xs_.shape)
    vals = np.where(inside, resp[bins, np.clip(ys_, 0, h - 1), np.clip(xs_, 0, w - 1)], 0)
    sc = vals.sum(axis=3).reshape(len(cx), -1)
    npos = len(ox)
    tie = np.abs(np.arange(na) - n_steps).repeat(npos) * 0.01
    k = np.argmax(sc - tie[None, :], axis=1)
    ai = k // npos
    rows = np.arange(len(cx))
    best = sc[rows, k]
    plateau = sc.reshape(len(cx), na, npos)[rows, ai] == best[:, None]
    px = (plateau * ox).sum(axis=1) / plateau.sum(axis=1)
    py = (plateau * oy).sum(axis=1) / plateau.sum(axis=1)
    return cx + px, cy + py, thetas[rows, ai], best / (4.0 * nf)


@pytest.mark.parametrize("spread", [1, 3, 0])
def test_tracking_equals_numpy_inside_and_at_the_borders(scene: tuple[shape.ShapeModel, np.ndarray, list],
                                                         spread: int) -> None:
    """``spread`` 0: random responses, non-zero up to the outermost pixels (border off-by-ones show)."""
    model, img, truth = scene
    lv = 2
    pyr = pyramid(img, lv + 1)
    resp = spread_max(response_maps(pyr[lv], model.params.min_contrast * GRAD_PER_CONTRAST, spread=1),
                      max(spread, 1))
    if spread == 0:
        resp = np.random.default_rng(2).integers(1, 5, resp.shape).astype(np.uint8)
    lm = model.levels[lv]
    rng = np.random.default_rng(7)
    s = 2.0 ** lv
    # near each true pose (two cut by the border) and at random places, some outside the image
    cx = np.array([int(round(t.u_px / s)) + d for t in truth for d in (-1, 0, 2)]
                  + list(rng.integers(-5, pyr[lv].shape[1] + 5, 20)), dtype=np.int64)
    cy = np.array([int(round(t.v_px / s)) + d for t in truth for d in (0, 1, -2)]
                  + list(rng.integers(-5, pyr[lv].shape[0] + 5, 20)), dtype=np.int64)
    th = np.array([math.radians(t.angle_deg) + d for t in truth for d in (0.0, 0.03, -0.05)]
                  + list(rng.uniform(-math.pi, math.pi, 20)))
    k_s = rng.uniform(0.9, 1.1, len(cx))
    for n_steps, reach in ((2, 2), (1, 1)):
        got = track(resp, lm, cx, cy, th, n_steps, reach, k_s)
        want = _track_numpy(resp, lm, cx, cy, th, n_steps, reach, k_s)
        for g, w in zip(got, want, strict=True):
            np.testing.assert_allclose(g, w, rtol=0, atol=1e-12)
    # the parts cut by the border are tracked to a real score, not zero
    assert got[3][3:9].min() > 0.3 or spread == 0


def test_climbing_reaches_a_pose_beyond_one_tracking_window(scene: tuple[shape.ShapeModel, np.ndarray, list]) -> None:
    """A coarse peak several pixels from the part (a partly hidden part's peak slides along its
    visible edges): one +-2 px window stops on its edge, climbing goes on to the part."""
    from vision.shape.tracking import climb

    model, img, truth = scene
    lv = 2
    pyr = pyramid(img, lv + 1)
    resp = spread_max(response_maps(pyr[lv], model.params.min_contrast * GRAD_PER_CONTRAST, spread=1), 3)
    lm = model.levels[lv]
    s = 2.0 ** lv
    t = truth[0]
    cx = np.array([int(round(t.u_px / s)) + 6], dtype=np.int64)
    cy = np.array([int(round(t.v_px / s)) - 3], dtype=np.int64)
    th = np.array([math.radians(t.angle_deg) + 3 * lm.angle_step])
    k = np.ones(1)
    x1, y1, t1, s1 = track(resp, lm, cx, cy, th, 2, 2, k)
    x2, y2, t2, s2 = climb(resp, lm, cx, cy, th, 2, k)
    assert math.hypot(x1[0] * s - t.u_px, y1[0] * s - t.v_px) > 2 * s  # one window does not reach
    assert math.hypot(x2[0] * s - t.u_px, y2[0] * s - t.v_px) <= 1.5 * s
    assert abs(scenes.wrap_deg(math.degrees(t2[0]) - t.angle_deg)) <= math.degrees(lm.angle_step)
    assert s2[0] > s1[0] + 0.1


def _top_maxima_numpy(planes: np.ndarray, nh: int, thr: int, circular: bool) -> tuple[np.ndarray, ...]:
    """The dilate-and-gather local maxima of the numpy top level (planes: (A, nh + 1, nw), last row 0)."""
    done, rows, nw = planes.shape
    dil = cv2.dilate(planes.reshape(done * rows, nw), np.ones((3, 3), np.uint8)).ravel()
    flat = planes.ravel()
    idx = np.flatnonzero(flat >= thr)
    idx = idx[flat[idx] >= dil[idx]]
    plane = rows * nw
    ai = idx // plane
    if done > 1:
        for step in (-1, 1):
            nb = ai + step
            wrap = (nb < 0) | (nb >= done)
            nbi = idx + step * plane
            if circular:
                nbi = np.where(wrap, idx + step * plane - np.sign(step) * done * plane, nbi)
                ok = flat[idx] >= dil[nbi]
            else:
                ok = wrap | (flat[idx] >= dil[np.clip(nbi, 0, len(dil) - 1)])
            idx, ai = idx[ok], ai[ok]
    rem = idx - ai * plane
    return ai, rem // nw, rem % nw, flat[idx].astype(np.int64)


@pytest.mark.parametrize("circular", [True, False])
def test_top_level_maxima_equal_numpy_with_plateaus(circular: bool) -> None:
    rng = np.random.default_rng(11)
    na, nh, nw = 9, 30, 41
    # coarse values: many equal neighbours (the spread responses make such plateaus)
    planes = np.zeros((na, nh + 1, nw), np.uint8)
    planes[:, :nh] = (rng.integers(0, 6, (na, nh, nw)) * 10).astype(np.uint8)
    planes[3, 10:13, 20:23] = 90  # a 3x3 plateau: all its cells are maxima
    dil = cv2.dilate(planes.reshape(na * (nh + 1), nw), np.ones((3, 3), np.uint8)).reshape(planes.shape)
    got = sk.top_maxima(planes, dil, nh, 20, circular)
    want = _top_maxima_numpy(planes, nh, 20, circular)
    for g, w in zip(got, want, strict=True):
        np.testing.assert_array_equal(g, w)
    assert len(got[0]) > 9 and np.count_nonzero(got[3] == 90) == 9


def test_top_level_maxima_read_the_accumulators_rows_in_place() -> None:
    """The search passes the accumulator's rows as they are (wider than the planes: wrapped garbage past
    column nw) and dilates the strided view of their first nw columns: the same maxima as on a copy."""
    rng = np.random.default_rng(12)
    na, nh, nw, wp = 7, 25, 33, 48
    wide = np.zeros((na, nh + 1, wp), np.uint8)
    wide[:, :nh] = (rng.integers(0, 6, (na, nh, wp)) * 10).astype(np.uint8)
    wide[:, :nh, nw:] = 250  # garbage past the planes, higher than any score: must be neither read nor a border
    planes = np.ascontiguousarray(wide[:, :, :nw])
    dil = cv2.dilate(planes.reshape(na * (nh + 1), nw), np.ones((3, 3), np.uint8)).reshape(planes.shape)
    view = cv2.dilate(wide.reshape(na * (nh + 1), wp)[:, :nw], np.ones((3, 3), np.uint8),
                      borderType=cv2.BORDER_CONSTANT | cv2.BORDER_ISOLATED).reshape(na, nh + 1, nw)
    np.testing.assert_array_equal(view, dil)
    for circular in (True, False):
        got = sk.top_maxima(wide, view, nh, 20, circular)
        want = sk.top_maxima(planes, dil, nh, 20, circular)
        for g, w in zip(got, want, strict=True):
            np.testing.assert_array_equal(g, w)
        assert len(got[0]) > 0 and int(got[2].max()) < nw


@pytest.mark.parametrize("nf", [24, 22, 3])
def test_top_level_sums_equal_numpy_adds(nf: int) -> None:
    rng = np.random.default_rng(5)
    nb, L, na, run = N_BINS, 4000, 6, 2500
    padf = rng.integers(0, 5, (nb, L)).astype(np.uint8)
    b = rng.integers(0, nb, (na, nf)).astype(np.int64)
    start = rng.integers(0, L - run, (na, nf)).astype(np.int64)
    lin = np.zeros((na, run + 100), np.uint8)
    sk.accumulate_top(padf, b, start, run, lin, 1, na)  # angle 0 left out: stays zero
    want = np.zeros_like(lin)
    for a in range(1, na):
        for k in range(nf):
            want[a, :run] += padf[b[a, k], start[a, k]:start[a, k] + run]
    np.testing.assert_array_equal(lin, want)
    assert lin[1:, :run].max() > 4 * nf * 0.6  # sums of many features, no wrap-around (4 * 24 < 256)


def test_perspective_fit_equals_numpy(scene: tuple[shape.ShapeModel, np.ndarray, list]) -> None:
    model, img, truth = scene
    lm = model.levels[0]
    t = truth[0]
    H = scenes.tilt_homography(SIZE, 4.0, 30.0)
    warped = cv2.warpPerspective(img, H, SIZE, flags=cv2.INTER_LINEAR)
    p = H @ np.array([t.u_px, t.v_px, 1.0])
    x0, y0 = int(p[0] / p[2]) - 130, int(p[1] / p[2]) - 130
    img_f = warped[y0:y0 + 261, x0:x0 + 261].astype(np.float32)
    args = (img_f, np.ascontiguousarray(lm.points), np.ascontiguousarray(lm.normals), p[0] / p[2] - x0 + 0.3,
            p[1] / p[2] - y0 - 0.2, math.radians(t.angle_deg) + 0.004, 1.0, model.params.min_contrast)
    want = refine._perspective_fit(*args)
    got = fit_kernels.perspective_fit(*args, CENTROID_HALF_WIDTH)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)
    assert abs(got[0] - args[3]) + abs(got[1] - args[4]) > 0.05  # it moved: the test exercises the fit


@pytest.mark.parametrize("spread", [1, 3])
def test_response_maps_equal_the_opencv_lookups(scene: tuple[shape.ShapeModel, np.ndarray, list],
                                                spread: int) -> None:
    """The compiled response planes and per-bin max filter against masks, ``cv2.LUT`` and one dilate."""
    from vision.image import gradients
    from vision.shape.responses import _RESPONSE_TABLE

    _, img, _ = scene
    lvl = pyramid(img, 2)[1]
    thr = 3.0
    gx, gy = gradients(lvl, 0.0)
    mag = cv2.magnitude(gx, gy)
    q = cv2.convertScaleAbs(cv2.phase(gx, gy, angleInDegrees=True), alpha=4.0 * N_BINS / 180.0, beta=-0.5)
    q = cv2.bitwise_and(q, 4 * N_BINS - 1)
    q[mag < thr] = 4 * N_BINS
    lut = np.zeros((N_BINS, 1, 256), np.uint8)
    lut[:, 0, :4 * N_BINS + 1] = _RESPONSE_TABLE
    want = np.stack([cv2.LUT(q, lut[b]) for b in range(N_BINS)])
    if spread > 1:
        h, w = q.shape
        stack = np.zeros((N_BINS, h + 1, w), np.uint8)
        stack[:, :h] = want
        want = cv2.dilate(stack.reshape(-1, w), np.ones((3, 3), np.uint8)).reshape(N_BINS, h + 1, w)[:, :h]
    got = response_maps(lvl, thr, spread=spread)
    np.testing.assert_array_equal(got, want)
    assert np.count_nonzero(got == 4) > 1000 and np.count_nonzero(got == 0) > 1000


def _stage_b_numpy(img_f: np.ndarray, ms: np.ndarray, ns: np.ndarray, pose: tuple[float, float, float, float],
                   s0: float, max_scale_dev: float, min_contrast: float, fit_scale: bool, iterations: int,
                   radius: float, vis_margin: float) -> tuple[float, float, float, float]:
    """The numpy centroid Gauss-Newton loop that ``fit_kernels.fit_stage_b`` replaced in ``refine_lsq``."""
    x, y, th, sc = pose
    H, W = img_f.shape
    dms = np.stack([ms[:, 1], -ms[:, 0]], axis=1)
    for _ in range(iterations):
        R = np.array([[math.cos(th), math.sin(th)], [-math.sin(th), math.cos(th)]])
        Rm = ms @ R.T
        q = sc * Rm + np.array([x, y])
        n = ns @ R.T
        off, S, clean = kernels.profile_centroids(img_f, q, n, CENTROID_HALF_WIDTH)
        vis = (q[:, 0] >= vis_margin) & (q[:, 1] >= vis_margin) & (q[:, 0] <= W - 1 - vis_margin) \
            & (q[:, 1] <= H - 1 - vis_margin)
        ok = clean & (np.abs(off) < 1.0) & (np.abs(S) >= 0.5 * min_contrast) & vis
        wgt = np.where(ok, (1 - off ** 2) ** 2, 0.0)
        if wgt.sum() < 6:
            break
        A, b = fit_kernels.gn_normal_equations(n, Rm, np.ascontiguousarray(dms @ R.T), sc, wgt, off)
        k = 4 if fit_scale else 3
        delta = np.linalg.solve(A[:k, :k] + np.eye(k) * 1e-9, b[:k])
        ds = float(delta[3]) if fit_scale else 0.0
        x, y, th = x + float(delta[0]), y + float(delta[1]), th + float(delta[2])
        sc = float(np.clip(sc + ds, s0 * (1 - max_scale_dev), s0 * (1 + max_scale_dev)))
        if abs(delta[0]) + abs(delta[1]) + (abs(delta[2]) + abs(ds)) * radius < 1e-3:
            break
    return x, y, th, sc


@pytest.mark.parametrize(("fit_scale", "iterations"), [(True, 1), (True, 3), (False, 3)])
def test_centroid_stage_equals_numpy(scene: tuple[shape.ShapeModel, np.ndarray, list], fit_scale: bool,
                                     iterations: int) -> None:
    model, img, truth = scene
    lm = model.levels[0]
    t = truth[0]
    x0, y0 = int(t.u_px) - 130, int(t.v_px) - 130
    img_f = np.ascontiguousarray(img[y0:y0 + 261, x0:x0 + 261].astype(np.float32))
    pose = (t.u_px - x0 + 0.4, t.v_px - y0 - 0.3, math.radians(t.angle_deg) + 0.003, 1.004)
    ms, ns = np.ascontiguousarray(lm.points), np.ascontiguousarray(lm.normals)
    args = (1.0, 0.1, model.params.min_contrast, fit_scale, iterations, lm.radius, 5.0)
    want = _stage_b_numpy(img_f, ms, ns, pose, *args)
    got = fit_kernels.fit_stage_b(img_f, ms, ns, *pose, 1.0, 0.1, model.params.min_contrast, fit_scale, iterations,
                                  lm.radius, 5.0, 260.0, 260.0, CENTROID_HALF_WIDTH)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)
    # it moved towards the truth (the test exercises the steps, not a no-op)
    assert math.hypot(got[0] - (t.u_px - x0), got[1] - (t.v_px - y0)) < 0.5 * math.hypot(0.4, 0.3)


def test_percentile75_is_numpys_percentile() -> None:
    from vision.shape import kernels

    rng = np.random.default_rng(4)
    for n in (1, 2, 3, 4, 5, 7, 100, 203):
        a = rng.gamma(2.0, 10.0, n)
        assert kernels.percentile75(a) == float(np.percentile(a, 75)), n


def test_magnitudes_are_the_bilinear_gradient_magnitudes() -> None:
    from vision.image import bilinear
    from vision.shape import kernels

    rng = np.random.default_rng(5)
    gx = rng.normal(0, 10, (40, 50)).astype(np.float32)
    gy = rng.normal(0, 10, (40, 50)).astype(np.float32)
    q = np.column_stack([rng.uniform(-3, 53, 300), rng.uniform(-3, 43, 300)])  # some past the border
    want = np.hypot(bilinear(gx, q[:, 0], q[:, 1]), bilinear(gy, q[:, 0], q[:, 1]))
    got = kernels.magnitudes(np.ascontiguousarray(np.dstack([gx, gy])), q)
    assert np.allclose(got, want, rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize("seed", range(3))
def test_run_sizes_equal_scipys_components(seed: int) -> None:
    """The verification's runs of evidence (``run_sizes``, union-find) are scipy's connected
    components of the pairs whose both ends are evidenced, counted over the evidenced points."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    rng = np.random.default_rng(seed)
    n = 300
    a = rng.integers(0, n, 400).astype(np.int64)
    b = ((a + rng.integers(1, 4, 400)) % n).astype(np.int64)  # chain-like links
    ev = rng.uniform(size=n) < 0.7
    got = sk.run_sizes(n, a, b, ev)
    both = ev[a] & ev[b]
    _, lab = connected_components(coo_matrix((np.ones(int(both.sum())), (a[both], b[both])), shape=(n, n)),
                                  directed=False)
    size = np.bincount(lab[ev], minlength=n)
    want = np.where(ev, size[lab], 0)
    assert np.array_equal(got, want)
    assert got[~ev].sum() == 0 and got[ev].min() >= 1

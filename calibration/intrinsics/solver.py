"""``calibrate``: the public intrinsics solver (see the package docstring)."""

from __future__ import annotations

import time
from collections.abc import Sequence

import numpy as np

from calibration.camera_model import MODEL_NAMES, N_DIST
from calibration.geometry import make_transform
from calibration.intrinsics.model import (
    BundleProblem,
    camera_from_vector,
    marginals,
    normal_equations_at,
    param_names,
)
from calibration.intrinsics.results import (
    F64,
    JACKKNIFE_GROUPS,
    JACKKNIFE_MIN_COVER,
    JACKKNIFE_MIN_VIEWS,
    MIN_POINTS_PER_VIEW,
    MIN_VIEWS,
    IntrinsicsError,
    IntrinsicsResult,
    fin,
)
from calibration.intrinsics.uncertainty import (
    cell_grid,
    coverage_counts,
    jackknife_projection_rms,
    projection_uncertainty,
    uncertainty_summary,
)
from calibration.intrinsics.views import (
    CONSISTENT_FACTOR,
    ViewData,
    base_weights,
    collect_views,
    flag_outliers,
    reject_outlier_points,
    set_weights,
    solve_views,
    weighting_sigmas,
)
from calibration.observations import SYSTEMATIC_FLOOR, Detection, systematic_floor_px
from calibration.targets import Target
from calibration.verdict import assess

REWEIGHT_MARGIN = 1.25
"""The weights are recomputed when the residuals' unexplained error exceeds the default floor by this factor."""

# --------------------------------------------------------------------------------------------
# the public solver


def calibrate(detections: Sequence[Detection], target: Target, model: str = "opencv5", *,
              image_size: tuple[int, int] | None = None, drop_outliers: bool = False,
              jackknife: bool = True, board_warp: bool = False,
              spline_grid: tuple[int, int, float] | None = None, reject_views: bool = False,
              regularise: bool = False) -> IntrinsicsResult:
    """Calibrate one camera from detections of ``target`` (see the module docstring).

    ``jackknife``: also estimate the projection uncertainty by a grouped view-level jackknife and
    scale the analytic covariance up when the jackknife's value is larger.

    ``board_warp``: the target may be bowed (mrcal's two-parameter parabolic warp,
    ``kernels``): solve its two heights with the intrinsics and report them
    (``IntrinsicsResult.board_warp``); the camera's covariance is marginalised over them. Whether a
    set needs it is for cross-validation to say (``select_model``), not the RMS (it always drops).

    ``model="splined"``: mrcal's splined stereographic model (``splined_solver.calibrate_splined``;
    ``spline_grid = (Nx, Ny, fov_x_deg)`` fixes its grid, default chosen from the data); refused
    with the reason on sets that cannot carry it.

    ``reject_views``: remove views whose leave-one-out influence on the projection is beyond what
    the solve's uncertainty predicts (``influence``: a chi-square test at a 1 % false-alarm rate
    over the set), one at a time, keeping the set's coverage; each says why in ``views`` and the
    test's summary is ``IntrinsicsResult.view_rejection``.

    ``regularise``: mrcal's regularisation (``model.regularisation``; opencv5 and opencv8): a small
    penalty holding the distortion coefficients (opencv8's rational denominator k4-k6 five times
    harder) near 0 and the principal point near the image centre, weighed so that it costs ~0.25 % of
    the data's chi^2 at their normal values. The covariance is then the regularised (posterior) one:
    the prior's information adds to the data's (``docs/conventions.md``, camera models).

    Raises IntrinsicsError with a message saying what to do when the data cannot determine
    the model (fewer than 3 usable views, too few points, all views parallel...).
    """
    t0 = time.perf_counter()
    if model not in MODEL_NAMES:
        raise IntrinsicsError(f"unknown model {model!r}; use one of {', '.join(MODEL_NAMES)}")
    if model == "splined":
        from calibration.intrinsics.splined_solver import calibrate_splined
        from calibration.splined import SplineLayout
        return calibrate_splined(detections, target, image_size=image_size, board_warp=board_warp,
                                 layout=None if spline_grid is None else SplineLayout(*spline_grid))
    views, results, size = collect_views(detections, target, image_size)
    if len(views) < MIN_VIEWS:
        raise IntrinsicsError(f"only {len(views)} usable view(s) of the target; a calibration needs "
                               f"at least {MIN_VIEWS} (10-20 recommended, tilted 20-45 deg about both axes)")
    n_lens = 4 + N_DIST[model]
    n_par = n_lens + (2 if board_warp else 0)
    n_obs = 2 * sum(len(v.X) for v in views)
    if n_obs <= n_par + 6 * len(views):
        raise IntrinsicsError(f"too few points ({n_obs // 2}) for {len(views)} views and the {model} model")
    reg = regularise
    p, c, R, t, iters = solve_views(model, size, views, target, board_warp=board_warp, regularise=reg)
    p, c, R, t, iters = _without_outlier_points(model, size, views, target, (p, c, R, t, iters))
    floor, (p, c, R, t, iters) = _reweight(model, size, views, target, n_par, (p, c, R, t, iters))
    if drop_outliers:
        p0_res = (p.project(c, R, t) - p.obs)
        pt_out, view_out = flag_outliers(p, p0_res, base_weights(views))
        if np.any(pt_out) or np.any(view_out):
            kept: list[ViewData] = []
            keep_R, keep_t = [], []
            for k, v in enumerate(views):
                if view_out[k]:
                    results[v.index].reason = "outlier view (RMS > 3x median), dropped"
                    results[v.index].outlier = True
                    continue
                m = ~pt_out[p.starts[k]:p.starts[k + 1]]
                if m.sum() < MIN_POINTS_PER_VIEW:
                    results[v.index].reason = "too few points left after dropping outliers"
                    continue
                results[v.index].n_outlier_points = int((~m).sum())
                kept.append(ViewData(v.index, v.image, v.ids[m], v.X[m], v.uv[m], v.ellipse,
                                     None if v.w is None else v.w[m], None if v.sigma is None else v.sigma[m]))
                keep_R.append(R[k])
                keep_t.append(t[k])
            if len(kept) < MIN_VIEWS:
                raise IntrinsicsError(f"only {len(kept)} views left after dropping outliers; "
                                       f"need at least {MIN_VIEWS}")
            views = kept
            start = (c, np.array(keep_R), np.array(keep_t))
            p, c, R, t, it2 = solve_views(model, size, views, target, start=start, regularise=reg)
            iters += it2
            p, c, R, t, iters = _without_outlier_points(model, size, views, target, (p, c, R, t, iters))
            floor, (p, c, R, t, iters) = _reweight(model, size, views, target, n_par, (p, c, R, t, iters))
    view_rejection = None
    if reject_views:
        from calibration.intrinsics.influence import reject_influential_views
        views, (p, c, R, t, iters), view_rejection = reject_influential_views(
            model, size, views, results, target, n_lens, (p, c, R, t, iters))
    # final Jacobian, covariance
    free = np.ones(n_par, dtype=bool)
    nrm, r = normal_equations_at(p, c, R, t, free)
    n_kept = 2 * int(np.sum(p.weights() > 0))
    dof = max(n_kept - n_par - 6 * p.n_views, 1)
    sigma2 = float(np.sum(r * r)) / dof
    S_inv, pose_cov = marginals(nrm)
    cov_all = sigma2 * S_inv
    cov = cov_all[:n_lens, :n_lens]              # the camera's, marginalised over the warp
    camera = camera_from_vector(model, size, c[:n_lens])
    res = (p.project(c, R, t) - p.obs)
    pt_out, view_out = flag_outliers(p, res, base_weights(views))
    all_uv = []
    for k, v in enumerate(views):
        sl = slice(p.starts[k], p.starts[k + 1])
        vr = results[v.index]
        vr.used = True
        vr.n_points = len(v.X)
        e = res[sl]
        vr.rms_px = float(np.sqrt(np.mean(np.sum(e * e, axis=1))))
        vr.T_cam_target = make_transform(R[k], t[k])
        vr.ids, vr.uv, vr.residuals_px = v.ids, v.uv, e
        if v.sigma is not None and len(v.sigma):
            vr.corner_sigma_px = float(np.median(v.sigma))
        vr.n_outlier_points = max(vr.n_outlier_points, int(pt_out[sl].sum()))
        if view_out[k]:
            vr.outlier = True
            vr.reason = "outlier view: RMS > 3x the median view RMS (drop_outliers removes it)"
        all_uv.append(v.uv)
    rms = float(np.sqrt(np.mean(np.sum(res * res, axis=1))))
    points_uv = np.vstack(all_uv)
    coverage = coverage_counts(size, points_uv)
    unc, umap = uncertainty_summary(camera, cov, coverage, points_uv)
    unc["projection_rms_analytic_px"] = unc["projection_rms_px"]
    unc["inflation"] = 1.0
    if jackknife and len(views) >= JACKKNIFE_MIN_VIEWS:
        pts = _robustly_covered(size, views, coverage.shape[1])
        j = jackknife_projection_rms(camera, nrm, pts, JACKKNIFE_GROUPS)
        a_same = _rms(projection_uncertainty(camera, cov, pts, np.ones(len(pts), dtype=bool)))
        a = unc["projection_rms_px"]
        # The jackknife of G replicates is itself noisy (relative sd of its RMS ~ 1 / sqrt(2 (G - 1)))
        # and biased upwards; taking max(analytic, jackknife) on every set over-reported sets whose
        # errors are independent (the circle plate ~2x more). Inflate only when it is significantly larger.
        g = min(len(views), JACKKNIFE_GROUPS)
        significant = 1.0 + 2.0 / np.sqrt(2.0 * (g - 1))
        if a and a_same > 0 and np.isfinite(j) and j > significant * a_same:
            # Detection errors correlated within a view make the analytic covariance optimistic;
            # the view-level jackknife sees them. Scale the analytic covariance up to match,
            # comparing both on the same cells (see _robustly_covered).
            f = j / a_same
            cov = cov * f**2
            cov_all = cov_all * f**2
            unc, umap = uncertainty_summary(camera, cov, coverage, points_uv)
            unc["inflation"] = f
        unc["projection_rms_analytic_px"] = a
        unc["projection_rms_jackknife_px"] = fin(j)
        unc["jackknife_cells"] = int(len(pts))
    if floor is not None:
        unc["systematic_floor_px"] = floor
    names = param_names(model)
    sig = {n: float(np.sqrt(max(cov[i, i], 0.0))) for i, n in enumerate(names)}
    normals = R[:, :, 2]
    verdict = assess(n_views=len(views), size=size, coverage=coverage, normals=normals, sigmas=sig,
                     values=dict(zip(names, c[:n_lens].tolist(), strict=True)), uncertainty=unc,
                     n_outlier_views=int(view_out.sum()), model=model)
    del pose_cov
    for k in (view_rejection or {}).get("kept_significant", []):
        verdict["advice"].append({"code": "influential_view_kept",
                                  "message": f"{k['image']} moves the projection {k['shift_px']} px where one view "
                                             f"is predicted to move it {k['predicted_px']} px (a sheared or blurred "
                                             f"view?), but it was kept: {k['kept_because']}"})
    warp = None
    if board_warp:
        sw = np.sqrt(np.maximum(np.diag(cov_all)[n_lens:], 0.0))
        warp = {"height_mm": [round(float(x) * 1000.0, 4) for x in c[n_lens:]],
                "sigma_mm": [round(float(x) * 1000.0, 4) for x in sw],
                "model": "z += w0 * 4 xr (1 - xr) + w1 * 4 yr (1 - yr), xr, yr in [0, 1] across the target"}
    reg_info = None
    if p.prior_w is not None:
        reg_info = {"rule": "mrcal's: distortion toward 0 (opencv8's k4-k6 5x harder), principal point toward the "
                            "image centre, each group ~0.25 % of the data's chi^2 at 1 px and its normal value "
                            "(distortion 2, centre offset 500 px)",
                    "weights_px": dict(zip(names, [round(float(x), 6) for x in p.prior_w], strict=True)),
                    "cost_share": round(p.prior_cost(c) / max(float(np.sum(r * r)), 1e-300), 6)}
    return IntrinsicsResult(camera=camera, rms_px=rms, sigma_px=float(np.sqrt(sigma2 / 2)), views=results,
                            param_names=names, covariance=cov, uncertainty=unc, verdict=verdict,
                            coverage=coverage, uncertainty_map_px=umap, iterations=iters,
                            time_s=time.perf_counter() - t0, board_warp=warp, view_rejection=view_rejection,
                            regularisation=reg_info)


Solved = tuple[BundleProblem, F64, F64, F64, int]


def _reweight(model: str, size: tuple[int, int], views: list[ViewData], target: Target, n_par: int,
              solved: Solved) -> tuple[float | None, Solved]:
    """Re-weight by the error the points' own uncertainties do not explain, and re-solve.

    The detectors' per-point uncertainties cover the random part only. Where the residuals are
    much larger (a lens the model does not fit to that precision, a board that is not flat,
    JPEG), that unexplained error ``tau`` (``systematic_floor_px``) is common to all points, and
    weighting by the small stated uncertainties alone lets a few close, sharp views dominate
    for no gain: on the real udacity 9x6 set (residuals 0.86 px, stated 0.003 px) the folds then
    cross-validated 12.1 px apart against 8.0 unweighted. With ``tau`` added to every point's
    uncertainty the weights come back to nearly uniform there, and stay as they were where the
    stated uncertainties explain the residuals (renders). Returns ``tau`` (None without
    uncertainties) and the (re-)solved problem."""
    s_all = weighting_sigmas(views)
    p, c, R, t, iters = solved
    if s_all is None:
        return None, solved
    keep = p.weights() > 0                       # points weighted out as outliers do not count
    res = p.project(c, R, t) - p.obs
    tau = systematic_floor_px(res[keep], s_all[keep], n_par + 6 * len(views))
    med = float(np.median(s_all[keep])) if np.any(keep) else float(np.median(s_all))
    if tau <= REWEIGHT_MARGIN * SYSTEMATIC_FLOOR * med:
        return tau, solved
    if tau > CONSISTENT_FACTOR * med:
        # The stated precision explains next to nothing of the residuals (a model that does not
        # fit the lens, a board that is not flat): even the floor-softened weights still favoured
        # the sharp centre over the blurred edges (GoPro 8x6, opencv5: cross-validation 6.9 px
        # weighted against 4.4 px uniform), so every point weighs the same.
        for v in views:
            v.w = None
    else:
        set_weights(views, floor_px=tau)
    p, c, R, t, it2 = solve_views(model, size, views, target, start=(c, R, t), regularise=p.prior_w is not None)
    return tau, (p, c, R, t, iters + it2)


def _without_outlier_points(model: str, size: tuple[int, int], views: list[ViewData], target: Target,
                            solved: Solved) -> Solved:
    """Weight out outlier points (``reject_outlier_points``) and re-solve, until the set is
    stable (at most three rounds)."""
    p, c, R, t, iters = solved
    for _ in range(3):
        if not reject_outlier_points(views, p, c, R, t):
            break
        p, c, R, t, it = solve_views(model, size, views, target, start=(c, R, t),
                                     regularise=p.prior_w is not None)
        iters += it
    return p, c, R, t, iters


def _robustly_covered(size: tuple[int, int], views: list[ViewData], nx: int) -> F64:
    """Centres of the grid cells that at least ``JACKKNIFE_MIN_COVER`` views observe (fewer cells
    are relaxed to 2, then 1). Leaving out a view must not leave the jackknife extrapolating into
    a cell only that view saw: there every replicate without it moves a lot, which is the
    uncertainty of a calibration without that view, not of this one (it over-reported small
    targets such as the circle plate several-fold)."""
    grid, _, _ = cell_grid(size, nx)
    n_cover = np.sum([coverage_counts(size, v.uv, nx).reshape(-1) > 0 for v in views], axis=0)
    for need in (JACKKNIFE_MIN_COVER, 2, 1):
        pts = grid[n_cover >= need]
        if len(pts) >= 4:
            return pts
    return grid[n_cover >= 1]


def _rms(a: F64) -> float:
    a = a[np.isfinite(a)]
    return float(np.sqrt(np.mean(a * a))) if a.size else 0.0

"""The width of the splined model's prior, knot by knot, from the data's own departure from the start lens.

The splined solve (``splined_solver``) pulls every control value towards ``c0``, the spline of its parametric
start (fisheye4), with a width of ``PRIOR_PX`` pixels: a control value that far off costs as one observation
off by the noise. A single width is wrong for a real lens: fisheye4 fits the centre of a fisheye to a pixel
and its edge to several (mrcal's Samyang 12 mm: the well-observed knots depart from fisheye4 by 0.9 px RMS
within ``|u| < 1`` and by 4.4 px at ``|u|`` 1.5-1.8), so a 3 px prior pulls the data-rich outer knots
towards a lens the data reject there.

The rule (empirical Bayes by ring, one pass): after the first solve, the knots are grouped in rings of
``RING_KNOTS`` knot spacings of ``|u|`` (the stereographic radius: the lens's departure from a radial
start grows with it). In each ring the *data-carried* control values (their observations' information is
at least ``CARRIED_FACTOR`` times the prior's) give the departure's spread,
``tau^2 = mean(dev^2 - sd^2)`` (px; ``sd`` their uncertainty). Every control value of the ring then gets
the width ``max(PRIOR_PX, tau)``: never tighter than before, looser only where the data themselves show
the lens departing from the start by more. A ring with fewer than ``MIN_CARRIED`` data-carried values
keeps ``PRIOR_PX`` (its knots are the ones the prior is for: the sparse edge, where the cross-validated
halves would otherwise fold). The solve is then repeated from the first solution. Nothing here is read
off a set's RMS: the widths are the data's spread of departures, and the cross-validation that chose
``PRIOR_PX`` still governs the knots without data.
"""

from __future__ import annotations

from typing import Final

import numpy as np
import scipy.linalg
import scipy.sparse as sp

from calibration.intrinsics.results import F64

RING_KNOTS: Final = 2.0
"""Ring width in knot spacings."""
CARRIED_FACTOR: Final = 10.0
"""A control value is carried by the data when their information on it is this many times the prior's."""
MIN_CARRIED: Final = 8
"""Data-carried control values a ring needs before its own spread sets its width."""


def ring_widths(knot_radius: F64, dev_px: F64, data_info: F64, sd_px: F64, prior_info: float,
                prior_px: float, spacing: float) -> F64:
    """Per control value (2 Nx Ny: the x values, then the y values) the prior's width (px).

    ``knot_radius``: (Nx Ny,) each knot's ``|u|``; ``dev_px``: (2 Nx Ny,) the first solve's departure from the
    prior (px); ``data_info``: (2 Nx Ny,) the observations' information on each value (diagonal of
    ``Jo^T Jo``); ``sd_px``: their 1-sigma uncertainty (px); ``prior_info``: the prior row's information
    (``a^2``); ``spacing``: the knot spacing (stereographic units)."""
    r = np.concatenate([knot_radius, knot_radius])
    ring = np.floor(r / (RING_KNOTS * spacing)).astype(np.int64)
    carried = data_info >= CARRIED_FACTOR * prior_info
    width = np.full(len(r), float(prior_px))
    for k in np.unique(ring):
        sel = ring == k
        use = sel & carried
        if use.sum() < MIN_CARRIED:
            continue
        tau = float(np.sqrt(max(np.mean(dev_px[use] ** 2 - sd_px[use] ** 2), 0.0)))
        width[sel] = max(float(prior_px), tau)
    return width


def prior_widths(H: F64, Jo: sp.csr_matrix, dev_px: F64, scale_px: float, prior_info: float, knot_radius: F64,
                 spacing: float, prior_px: float) -> F64:
    """``ring_widths`` from a solve's normal matrix ``H`` and weighted observation Jacobian ``Jo`` (both over
    the unknowns without the held core: the 2 Nx Ny control values first). ``dev_px``: the values' departure
    from the prior (px); ``scale_px``: px per unit of ``H^-1``'s square root (``f sigma``)."""
    nv = len(dev_px)
    d = np.sqrt(np.maximum(np.diag(H), 1e-300))
    try:                                  # diag of H^-1 from its Cholesky factor: column sums of (L^-1)^2
        L = scipy.linalg.cholesky(H / d[:, None] / d[None, :], lower=True, check_finite=False)
        Linv = scipy.linalg.solve_triangular(L, np.eye(len(d)), lower=True, check_finite=False)
    except np.linalg.LinAlgError:         # singular: no ring's spread can be trusted
        return np.full(nv, float(prior_px))
    sd_px = scale_px * np.sqrt(np.sum(Linv[:, :nv] ** 2, axis=0)) / d[:nv]
    sq = Jo[:, :nv].multiply(Jo[:, :nv])
    info = np.asarray(sq.sum(axis=0)).ravel()
    return ring_widths(knot_radius, dev_px, info, sd_px, prior_info, prior_px, spacing)

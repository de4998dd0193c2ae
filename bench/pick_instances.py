"""The real-image bench per instance: each match's pose against a reference measured again.

For every instance of the dev corpus that has an angle in ``measured_estimate`` the reference is a
rotation-and-sub-pixel NCC sweep of the taught patch (``bench.pick_reference.sweep``, started from the
estimate, never from a match). A row gives the estimate's and the reference's distance, the match's
position and angle error against the reference (at the estimate's reference point, angles modulo the
part's symmetry), the match's reported 1-sigma and the ratio actual / reported, the patch's
correlation and the two fits' disagreement (``Match.scores``: ``patch_ncc``, ``fit_chi2``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from bench.pick_cases import DATA, TARGET, Case, Found, TestImage, angle_diff, to_reference
from bench.pick_reference import REF_SIGMA, sweep
from vision.types import Match


@dataclass
class InstanceRow:
    image: str
    estimate: tuple[float, float, float]
    est_vs_ref: tuple[float, float] | None
    """The estimate's distance (px) and angle difference (deg) from the reference."""
    err: tuple[float, float] | None
    """The match's position (px) and angle (deg) error against the reference; None: not found."""
    sigma: tuple[float, float]
    """The match's reported 1-sigma: position (px), angle (deg)."""
    patch_ncc: float
    fit_chi2: float
    case: str = ""


def _roi_centre(case: Case, x: float, y: float, a_deg: float, mirrored: bool) -> tuple[float, float]:
    """The ROI centre of a part whose estimate's reference point lies at (x, y) turned by ``a_deg``."""
    u, v, w, h = case.roi
    d = np.array(case.info.reference_px) - np.array([u + w / 2.0, v + h / 2.0])
    if mirrored:
        d[0] = -d[0]
    c, s = math.cos(math.radians(a_deg)), math.sin(math.radians(a_deg))
    return x - (c * d[0] + s * d[1]), y - (-s * d[0] + c * d[1])


def instance_rows(case: Case, test: TestImage, img: np.ndarray, matches: list[Match]) -> list[InstanceRow]:
    """One row per estimated instance with an angle (the screw heads have none: no row)."""
    rows: list[InstanceRow] = []
    gate = 0.5 * min(case.roi[2], case.roi[3])
    sym = case.info.symmetry_deg
    for inst in test.instances:
        if inst.angle_deg is None:
            continue
        uc, vc = _roi_centre(case, inst.x, inst.y, inst.angle_deg, inst.mirrored)
        ref = sweep(case.teach_image(), case.roi, img, uc, vc, inst.angle_deg, inst.mirrored)
        if ref is None:
            continue
        rx, ry = to_reference(case, Found(ref.u_px, ref.v_px, ref.angle_deg, ref.ncc, inst.mirrored))
        est_vs = (math.hypot(inst.x - rx, inst.y - ry), angle_diff(inst.angle_deg, ref.angle_deg, sym))
        best: tuple[float, Match] | None = None
        for m in matches:
            mx, my = to_reference(case, Found(m.u_px, m.v_px, m.angle_deg, m.score, m.mirrored))
            d = math.hypot(mx - rx, my - ry)
            if d <= gate and m.mirrored == inst.mirrored and (best is None or d < best[0]):
                best = (d, m)
        name = f"{test.path.relative_to(DATA)} ({inst.x:.0f}, {inst.y:.0f})"
        if best is None:
            rows.append(InstanceRow(name, (inst.x, inst.y, inst.angle_deg), est_vs, None, (math.nan, math.nan),
                                    math.nan, math.nan, case.id))
            continue
        d, m = best
        rows.append(InstanceRow(name, (inst.x, inst.y, inst.angle_deg), est_vs,
                                (d, angle_diff(m.angle_deg, ref.angle_deg, sym)), (m.sigma_px, m.sigma_angle_deg),
                                m.scores.get("patch_ncc", math.nan), m.scores.get("fit_chi2", math.nan), case.id))
    return rows


def _ratio(e: float, s: float, ref: float = 0.0) -> float:
    """|error| over the reported 1-sigma (and the reference's own error, in quadrature)."""
    return abs(e) / math.hypot(s, ref) if s > 0 and math.isfinite(s) else math.nan


def instance_table(rows: list[InstanceRow]) -> list[str]:
    """The per-instance table and its summary (markdown lines)."""
    out = ["## Per instance: pose against a re-measured reference (default settings)", "",
           "Reference: a rotation-and-sub-pixel NCC sweep of the taught patch per instance "
           "(`bench/pick_reference.py`: 0.1-deg steps over +-2.5 deg and +-8 px around the estimate, "
           "sub-pixel parabolas in x, y and angle), carried to the estimate's reference point. 'ratio' is "
           "|error| / reported 1-sigma (honest: about 1 in RMS; the reference's own error, a few "
           "hundredths, is in the error too).", "",
           "| instance | estimate vs reference px / deg | error px | error deg | sigma px | sigma deg | ratio px "
           "| ratio deg | patch NCC | fit chi2 |",
           "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    rp: list[float] = []
    ra: list[float] = []
    qp: list[float] = []
    qa: list[float] = []
    within = found = 0
    for r in rows:
        ev = f"{r.est_vs_ref[0]:.2f} / {r.est_vs_ref[1]:+.2f}" if r.est_vs_ref else "-"
        if r.err is None:
            out.append(f"| {r.image} | {ev} | not found | - | - | - | - | - | - | - |")
            continue
        found += 1
        within += r.err[0] <= TARGET[0] and abs(r.err[1]) <= TARGET[1]
        a, b = _ratio(r.err[0], r.sigma[0]), _ratio(r.err[1], r.sigma[1])
        rp += [a] if math.isfinite(a) else []
        ra += [b] if math.isfinite(b) else []
        qa_, qb_ = _ratio(r.err[0], r.sigma[0], REF_SIGMA[0]), _ratio(r.err[1], r.sigma[1], REF_SIGMA[1])
        qp += [qa_] if math.isfinite(qa_) else []
        qa += [qb_] if math.isfinite(qb_) else []
        out.append(f"| {r.image} | {ev} | {r.err[0]:.2f} | {r.err[1]:+.2f} | {r.sigma[0]:.3f} | {r.sigma[1]:.3f} | "
                   f"{a:.1f} | {b:.1f} | {r.patch_ncc:.3f} | {r.fit_chi2:.2f} |")

    def rms(x: list[float]) -> float:
        return math.sqrt(sum(v * v for v in x) / len(x)) if x else math.nan

    def share(x: list[float]) -> str:
        return f"{sum(0.5 <= v <= 2.0 for v in x)} of {len(x)}" if x else "-"

    out += ["", f"Found {found} of {len(rows)} instances with a reference; within {TARGET[0]:g} px and "
            f"{TARGET[1]:g} deg of it: {within} of {found}. Actual / reported 1-sigma: RMS {rms(rp):.2f} "
            f"(position), {rms(ra):.2f} (angle); per instance within 0.5-2: {share(rp)} (position), {share(ra)} "
            f"(angle). With the reference's own error (`REF_SIGMA`: {REF_SIGMA[0]:g} px, {REF_SIGMA[1]:g} deg, "
            f"measured on renders) in quadrature: RMS {rms(qp):.2f} (position), {rms(qa):.2f} (angle); within "
            f"0.5-2: {share(qp)}, {share(qa)}."]
    return out + _per_case(rows)


def _per_case(rows: list[InstanceRow]) -> list[str]:
    """Actual / reported 1-sigma per case (RMS over its found instances; the reference's own error in
    quadrature, as the last column pair): is the 1-sigma honest (0.5-2) case by case."""
    out = ["", "Actual / reported 1-sigma per case (RMS over its found instances with a reference; target 0.5-2):",
           "", "| case | instances | position | angle | position, with the reference's error | angle, with it |",
           "| --- | --- | --- | --- | --- | --- |"]
    for cid in dict.fromkeys(r.case for r in rows):
        got = [r for r in rows if r.case == cid and r.err is not None]
        if not got:
            continue
        cols = []
        for k, ref in ((0, 0.0), (1, 0.0), (0, REF_SIGMA[0]), (1, REF_SIGMA[1])):
            v = [x for x in (_ratio(r.err[k], r.sigma[k], ref) for r in got if r.err) if math.isfinite(x)]
            cols.append(f"{math.sqrt(sum(x * x for x in v) / len(v)):.2f}" if v else "-")
        out.append(f"| {cid} | {len(got)} | " + " | ".join(cols) + " |")
    return out

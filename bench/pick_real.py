"""Real-image pick benchmark (issue 14): the shape matcher vs an OpenCV NCC rotation sweep.

Every case of ``tests/data/pick_real`` (17 photographs from 4 public sources; see each folder's
``cases.yaml`` and ``SOURCE.txt``): the part is taught once from the case's ROI, then searched
in each test image at the default settings. Columns: instances found / expected, false matches,
position and angle error against the corpus's ``measured_estimate`` (carried to the estimate's
own reference point, see ``bench/pick_cases.py``), and the in-process time per image.

The peer (``bench.ncc_baseline.Baseline``, the same as in ``bench/pick.py``): ``cv2.matchTemplate``
(TM_CCOEFF_NORMED, absolute value) over templates rotated about the ROI centre, 4 deg steps at
1/4 scale then 0.25 deg steps at full scale, parabolic sub-pixel peaks; teach and test images
are padded (border replicate) so templates and parts at the border fit. Same minimum score.

Every case is taught with ``TeachParams``' default colour mode (``auto``: the chroma channel where the taught
part is coloured against its background, the screw heads; grey otherwise), its images read in colour only
when its model is a colour one (``pick_cases.Case.colour``); the section "Colour" shows the colour cases
taught in grey, the previous default.

Hard variants of every test image (``pick_cases.VARIANTS``) and of whole cases resized to a half
and a quarter (``pick_cases.SIZES``: small parts) are summed per variant.

Run: ``.venv/bin/python bench/pick_real.py [--out bench/results/pick_real.md] [--no-baseline]``.
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.machine import cpu_model  # noqa: E402
from bench.ncc_baseline import Baseline  # noqa: E402
from bench.pick_cases import (  # noqa: E402
    DATA,
    SIZES,
    TARGET,
    VARIANTS,
    Case,
    Found,
    Scored,
    TestImage,
    load_cases,
    scaled,
    score,
    teach_model,
    teach_one,
    to_reference,
    with_colour,
)
from bench.pick_instances import InstanceRow, instance_rows, instance_table  # noqa: E402
from vision import shape  # noqa: E402
from vision.shape.model import TeachParams  # noqa: E402
from vision.shape.rim import rim_centre  # noqa: E402
from vision.types import Match, SearchParams  # noqa: E402

MIN_SCORE = SearchParams().min_score
DEFAULT_COLOUR = TeachParams().colour
OTHER_COLOUR = "grey" if DEFAULT_COLOUR != "grey" else "auto"
"""The colour mode of the section "Colour": the one of the two (grey, auto) the main tables do not use."""


@dataclass
class Tally:
    found: int = 0
    expected: int = 0
    false: int = 0
    bad: int = 0
    over: int = 0
    pos: list[float] = field(default_factory=list)
    ang: list[float] = field(default_factory=list)
    ms: list[float] = field(default_factory=list)
    cpu_ms: list[float] = field(default_factory=list)

    def add(self, s: Scored, ms: float, cpu_ms: float) -> None:
        self.found += s.found
        self.expected += s.expected
        self.false += s.false
        self.bad += s.out_of_tolerance
        self.over += s.over_target
        self.pos += s.pos_err
        self.ang += s.ang_err
        self.ms.append(ms)
        self.cpu_ms.append(cpu_ms)


def _max(xs: list[float]) -> str:
    return f"{max(abs(x) for x in xs):.2f}" if xs else "-"


def _med(xs: list[float]) -> float:
    return statistics.median(xs) if xs else float("nan")


class Ncc:
    """The NCC peer on padded images (a template or a part at the border still fits)."""

    def __init__(self, case: Case) -> None:
        u, v, w, h = case.roi
        self.pad = int(math.ceil(0.5 * math.hypot(w, h))) + 2
        p = self.pad
        teach = cv2.copyMakeBorder(case.teach_image(), p, p, p, p, cv2.BORDER_REPLICATE)
        self.base = Baseline.build(teach, (u + p, v + p, w, h))

    def find(self, img: np.ndarray) -> tuple[list[Found], float, float]:
        """Matches, wall ms, CPU ms."""
        t0, c0 = time.perf_counter(), time.process_time()
        p = self.pad
        big = cv2.copyMakeBorder(img, p, p, p, p, cv2.BORDER_REPLICATE)
        out = [Found(f.u_px - p, f.v_px - p, f.angle_deg, f.score) for f in self.base.find(big, MIN_SCORE)]
        return out, (time.perf_counter() - t0) * 1e3, (time.process_time() - c0) * 1e3


def _ours(model: shape.ShapeModel, img: np.ndarray, mirrored: bool, into: list[Match] | None = None
          ) -> tuple[list[Found], float, float, int]:
    """Matches, wall ms (``FindResult.elapsed_s``), CPU ms (the search's own process time), and the
    candidates the verification rejected (``into``: receives the matches themselves)."""
    res = shape.find(model, img, SearchParams(mirrored=mirrored))
    if into is not None:
        into += res.matches
    return ([Found(m.u_px, m.v_px, m.angle_deg, m.score, m.mirrored) for m in res.matches],
            res.elapsed_s * 1e3, res.stats.get("cpu_total_s", float("nan")) * 1e3, len(res.rejected))


def _pr(t: Tally) -> str:
    """Precision (found / (found + false)) and recall (found / expected) of a tally."""
    prec = t.found / (t.found + t.false) if t.found + t.false else float("nan")
    rec = t.found / t.expected if t.expected else float("nan")
    return f"precision {prec:.3f} ({t.found} / {t.found + t.false}), recall {rec:.3f} ({t.found} / {t.expected})"


def _mirrored_found(case: Case, test: TestImage, found: list[Found]) -> tuple[int, int, int]:
    """Reverse-side instances: (how many, found by any match, found by a mirrored match)."""
    gate = 0.5 * min(case.roi[2], case.roi[3])
    n = hit = hit_m = 0
    for i in test.instances:
        if not i.mirrored:
            continue
        n += 1
        near = [f for f in found if math.hypot(*(np.subtract(to_reference(case, f), (i.x, i.y)))) <= gate]
        hit += bool(near)
        hit_m += any(f.mirrored for f in near)
    return n, hit, hit_m


@dataclass
class Run:
    rows: list[str] = field(default_factory=list)
    mirror_rows: list[str] = field(default_factory=list)
    variants: dict[str, tuple[Tally, Tally]] = field(default_factory=dict)
    mirror: Tally = field(default_factory=Tally)
    mirrored_instances: list[int] = field(default_factory=lambda: [0, 0, 0])
    false_where: list[str] = field(default_factory=list)
    instances: list[InstanceRow] = field(default_factory=list)


def _row(name: str, test: TestImage, so: Scored, ms: float, cpu: float, rejected: int) -> str:
    return (f"| {name} | {test.expected_count} | {so.found} | {so.false} | {rejected} | {_max(so.pos_err)} | "
            f"{_max(so.ang_err)} | {so.over_target} / {so.out_of_tolerance} | {ms:.1f} | {cpu:.1f} |")


def _one_case(case: Case, run: Run, variants: dict[str, object], with_baseline: bool, label: str | None) -> None:
    """Search every test image of ``case`` under ``variants`` (``label``: the size variant's name)."""
    model = teach_model(case)  # from every view the case gives (one ROI: _views_section)
    ncc = Ncc(case) if with_baseline else None
    for test in case.tests:
        base_img = case.test_image(test)
        for vname, fn in variants.items():
            key = label or vname
            img = fn(base_img)  # type: ignore[operator]
            raw: list[Match] = []
            ours, ms, cpu, n_rej = _ours(model, img, False, raw)
            if vname == "original" and label is None:
                run.instances += instance_rows(case, test, img, raw)
            so = score(case, test, ours)
            run.variants.setdefault(key, (Tally(), Tally()))[0].add(so, ms, cpu)
            if so.false:
                run.false_where.append(f"{key}: {test.path.name} ({so.false})")
            st = None
            if ncc is not None:
                theirs, ms_b, cpu_b = ncc.find(img)
                st = score(case, test, theirs)
                run.variants[key][1].add(st, ms_b, cpu_b)
            if vname != "original" or label is not None:
                continue
            name = str(test.path.relative_to(DATA))
            r = _row(name, test, so, ms, cpu, n_rej)
            if st is not None:
                r += (f" {st.found} | {st.false} | {_max(st.pos_err)} | {_max(st.ang_err)} | "
                      f"{st.over_target} / {st.out_of_tolerance} | {ms_b:.0f} | {cpu_b:.0f} |")
            run.rows.append(r)
            mo, ms_m, cpu_m, n_rej_m = _ours(model, img, True)
            sm = score(case, test, mo)
            run.mirror.add(sm, ms_m, cpu_m)
            run.mirror_rows.append(_row(name, test, sm, ms_m, cpu_m, n_rej_m))
            n, hit, hit_m = _mirrored_found(case, test, mo)
            for j, x in enumerate((n, hit, hit_m)):
                run.mirrored_instances[j] += x
        print(f"  {label or ''} {case.id} {test.path.name}", file=sys.stderr, flush=True)


def run(with_baseline: bool) -> str:
    load0 = os.getloadavg()
    cases = [with_colour(c, DEFAULT_COLOUR) for c in load_cases()]
    out = Run()
    warm = shape.teach(cases[0].teach_image(), cases[0].roi)
    shape.find(warm, cases[0].teach_image(), SearchParams(mirrored=True))  # compiled kernels load once
    for case in cases:
        _one_case(case, out, dict(VARIANTS), with_baseline, None)
    for label, k in SIZES.items():
        for case in cases:
            _one_case(scaled(case, k), out, {"original": VARIANTS["original"]}, with_baseline, label)
    views = _views_section(cases) + [""] + _colour_section(cases)
    load1 = os.getloadavg()
    return _report(out, with_baseline, load0, load1, views)


def _views_section(cases: list[Case]) -> list[str]:
    """The cases whose teach image shows the part more than once (``more_teach_rois``: the screw heads'
    four heads) taught as before from their one ROI, every variant and size: what the several views
    (the main tables, ``vision.shape.multi.teach_many``) changed."""
    out = ["## One teach view against several (`more_teach_rois`)",
           "",
           "The main tables teach a part from every view of it that its case gives in the teach image "
           "(`bench.pick_cases.teach_model`: the edges most views show with the same contrast polarity, "
           "the views' average patch; only the screw heads give several). Here such a case taught from its "
           "one ROI, as before this round, default search settings, every variant and size (errors against "
           "`measured_estimate` as above).", "",
           "| case | variant | expected | found | false | max pos err px | over target / beyond tol | median CPU ms |",
           "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for case in (c for c in cases if c.more_rois):
        for label, k in [("original size", 1.0), *SIZES.items()]:
            c = case if k == 1.0 else scaled(case, k)
            model = teach_one(c)
            variants = VARIANTS if k == 1.0 else {"original": VARIANTS["original"]}
            for vname, fn in variants.items():
                t = Tally()
                for test in c.tests:
                    ours, ms, cpu, _ = _ours(model, fn(c.test_image(test)), False)
                    t.add(score(c, test, ours), ms, cpu)
                name = vname if k == 1.0 else label
                out.append(f"| {case.id}, one ROI | {name} | {t.expected} | {t.found} | {t.false} | {_max(t.pos)} | "
                           f"{t.over} / {t.bad} | {_med(t.cpu_ms):.1f} |")
    return out


def _colour_section(cases: list[Case]) -> list[str]:
    """The cases whose model ``TeachParams(colour="auto")`` makes of a colour channel (``vision.shape.colour``:
    the screw heads), taught with ``OTHER_COLOUR`` (the mode the main tables do not use) from their several
    views and from their one ROI, every variant and size."""
    out = [f"## Colour (`TeachParams(colour=\"{OTHER_COLOUR}\")` for the colour cases, `vision.shape.colour`)",
           "",
           f"The main tables teach with the default colour mode (`{DEFAULT_COLOUR}`). The cases whose automatic "
           "colour choice takes the chroma channel (the part against its background with the background's own "
           "colour, and so its shading, projected out: the screw heads; every other case stays grey) are here "
           f"taught with `{OTHER_COLOUR}` (a colour model's images in colour, B, G, R; a grey one's in grey), "
           "from their several views and from their one ROI, every variant and size ('texture' adds the same "
           "grey texture to every channel). CPU ms: `shape.find`'s own, the projection included.", "",
           "'rim fit': the rim measured after each found head's match (`vision.shape.rim.rim_centre`), its "
           "distance from the estimate (RMS, largest) and actual / reported 1-sigma (RMS).", "",
           "| case | variant | expected | found | false | max pos err px | over target / beyond tol | median CPU ms "
           "| rim fit: RMS / max err px | rim fit: actual / reported |",
           "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for base in cases:
        if not with_colour(base, "auto").colour:
            continue
        case = with_colour(base, OTHER_COLOUR)
        for views, teach_fn in (("several views", teach_model), ("one ROI", teach_one)):
            for label, k in [("original size", 1.0), *SIZES.items()]:
                c = case if k == 1.0 else scaled(case, k)
                model = teach_fn(c)
                variants = VARIANTS if k == 1.0 else {"original": VARIANTS["original"]}
                for vname, fn in variants.items():
                    t = Tally()
                    rim_err: list[float] = []
                    rim_ratio: list[float] = []
                    for test in c.tests:
                        img = fn(c.test_image(test))
                        got: list[Match] = []
                        ours, ms, cpu, _ = _ours(model, img, False, got)
                        t.add(score(c, test, ours), ms, cpu)
                        for i in test.instances:
                            near = [m for m in got if math.hypot(m.u_px - i.x, m.v_px - i.y) < 30.0 * c.scale]
                            fit = rim_centre(model, img, near[0]) if near else None
                            if fit is not None:
                                rim_err.append(math.hypot(fit.u_px - i.x, fit.v_px - i.y))
                                rim_ratio.append(rim_err[-1] / (math.sqrt(2.0) * fit.sigma_px))
                    name = vname if k == 1.0 else label
                    rims = (f"{_rms(rim_err):.2f} / {max(rim_err):.2f} ({len(rim_err)}) | {_rms(rim_ratio):.2f}"
                            if rim_err else "- | -")
                    out.append(f"| {case.id}, {views}, {OTHER_COLOUR} | {name} | {t.expected} | {t.found} | "
                               f"{t.false} | {_max(t.pos)} | {t.over} / {t.bad} | {_med(t.cpu_ms):.1f} | {rims} |")
    return out


def _rms(xs: list[float]) -> float:
    return math.sqrt(sum(x * x for x in xs) / len(xs)) if xs else float("nan")


def _targets(r: Run, with_baseline: bool) -> list[str]:
    o, t = r.variants["original"]
    n_m, hit_m, hit_mm = r.mirrored_instances
    n_all = sum(v[0].false for v in r.variants.values())
    pos_ok = o.found - o.over
    ncc = f" (NCC: {t.found} of {t.expected}, {t.false} false)" if with_baseline else ""
    ratio = _med(t.ms) / _med(o.ms) if with_baseline else float("nan")
    cpu_ratio = _med(t.cpu_ms) / _med(o.cpu_ms) if with_baseline else float("nan")
    return [
        "## Against the targets (issue 14)",
        "",
        "| target | result | verdict |",
        "| --- | --- | --- |",
        f"| every dev-corpus instance found at the default settings | {o.found} of {o.expected}{ncc} | "
        f"{'met' if o.found == o.expected else '**missed**'} |",
        f"| 0 false matches (originals, every hard variant and size) | {n_all}"
        + (f" ({'; '.join(r.false_where)})" if r.false_where else "")
        + (f"; NCC on the originals: {t.false}" if with_baseline else "")
        + f" | {'met' if n_all == 0 else '**missed**'} |",
        f"| the reverse-side key found with mirrored search on | {hit_m} of {n_m} found, {hit_mm} of them by the "
        f"mirrored model | {'met' if hit_mm == n_m else ('found, not as mirrored' if hit_m == n_m else '**missed**')}"
        " |",
        f"| position within {TARGET[0]:g} px, angle within {TARGET[1]:g} deg of `measured_estimate` | "
        f"{pos_ok} of {o.found} found instances (over target: {o.over}; beyond target + the estimate's own "
        f"accuracy: {o.bad}) | {'met' if o.over == 0 else '**missed**'} |",
        f"| (speed, no target here) median per image, NCC / ours | {ratio:.1f}x wall, {cpu_ratio:.1f}x CPU | - |",
    ]


def _report(r: Run, with_baseline: bool, load0: tuple[float, float, float],
            load1: tuple[float, float, float], views: list[str] | None = None) -> str:
    head = ("| image | expected | found | false | rejected | max pos err px | max angle err deg | over target / "
            "beyond tol | ms | CPU ms |")
    sep = "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"
    if with_baseline:
        head += (" NCC found | NCC false | NCC pos err | NCC angle err | NCC over target / beyond tol | NCC ms "
                 "| NCC CPU ms |")
        sep += " --- | --- | --- | --- | --- | --- | --- |"
    cmd = ".venv/bin/python bench/pick_real.py" + ("" if with_baseline else " --no-baseline")
    m = r.mirror
    lines = [
        "# Real-image pick benchmark (issue 14): shape matcher vs OpenCV NCC rotation sweep",
        "",
        f"`{cmd}` — the 12 test images of the 5 cases in `tests/data/pick_real` (4 public sources, "
        "licences beside the images), each part taught once from its case's ROI (the screw heads from the "
        "teach image's four heads, `more_teach_rois`), default settings "
        f"(min_score {MIN_SCORE}). Errors are against the corpus's `measured_estimate` (not ground "
        "truth: accurate to about +-0.5-1 px and +-0.5-1 deg; the screw heads only +-4 px and no angle), "
        "after carrying the match to the estimate's reference point; angles modulo the part's symmetry. "
        "'over target / beyond tol' count the found instances farther than the target (1 px, 1 deg) "
        "from the estimate, and farther than the target plus the estimate's own stated accuracy "
        "(+-0.5-1 px, +-0.5-1 deg; the screws +-4 px; the reverse-side key +-3 px, +-2 deg).",
        "",
        f"Machine: {cpu_model()}, {os.cpu_count()} cores shared with "
        f"other jobs; load average at start {load0[0]:.2f}, at end {load1[0]:.2f}. Times are "
        "in-process per image: wall (`FindResult.elapsed_s`) and this process's CPU time "
        "(`time.process_time`, steadier on a busy machine); the NCC peer timed around its call.",
        "",
        "## Default settings (mirrored search off)",
        "",
        head, sep, *r.rows,
        "",
        "'false': matches that are not an instance of the part (or lie beyond half the part's size from "
        "one); 'rejected': candidates that reached min_score and failed the verification "
        "(`vision/shape/verify.py`), never answered.",
        "",
        f"Precision / recall on the originals: cellctl {_pr(r.variants['original'][0])}"
        + (f"; NCC {_pr(r.variants['original'][1])}" if with_baseline else "") + ".",
        "",
        f"Over every variant and size: cellctl {_pr(_sum(v[0] for v in r.variants.values()))}"
        + (f"; NCC {_pr(_sum(v[1] for v in r.variants.values()))}" if with_baseline else "") + ".",
        "",
        "## Mirrored search on (`SearchParams(mirrored=True)`)",
        "",
        "| image | expected | found | false | rejected | max pos err px | max angle err deg | over target / beyond "
        "tol | ms | CPU ms |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
        *r.mirror_rows,
        f"| **all** | {m.expected} | {m.found} | {m.false} | - | {_max(m.pos)} | {_max(m.ang)} | {m.over} / {m.bad} | "
        f"{_med(m.ms):.1f} (median) | {_med(m.cpu_ms):.1f} (median) |",
        "",
        "## Hard variants (sums over the 12 images; default settings)",
        "",
        "The size rows resize teach and test images alike (area averaging): the parts are then a half "
        "or a quarter as large (the SICK double cross 43 x 26 px, then 21 x 13 px).",
        "",
        "| variant | expected | found | false | over target / beyond tol | median ms | median CPU ms |"
        + (" NCC found | NCC false | NCC over target / beyond tol | NCC median ms | NCC median CPU ms |"
           if with_baseline else ""),
        "| --- | --- | --- | --- | --- | --- | --- |" + (" --- | --- | --- | --- | --- |" if with_baseline else ""),
    ]
    for vname, (o, t) in r.variants.items():
        row = (f"| {vname} | {o.expected} | {o.found} | {o.false} | {o.over} / {o.bad} | {_med(o.ms):.1f} | "
               f"{_med(o.cpu_ms):.1f} |")
        if with_baseline:
            row += f" {t.found} | {t.false} | {t.over} / {t.bad} | {_med(t.ms):.0f} | {_med(t.cpu_ms):.0f} |"
        lines.append(row)
    lines += ["", *instance_table(r.instances), "", *(views or []), "", *_targets(r, with_baseline)]
    return "\n".join(lines) + "\n"


def _sum(ts: Iterable[Tally]) -> Tally:
    out = Tally()
    for t in ts:
        out.found += t.found
        out.expected += t.expected
        out.false += t.false
    return out


NOTES_MARK = "## Notes"


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--no-baseline", action="store_true", help="skip the (slow) OpenCV NCC peer")
    ap.add_argument("--out", default=None, help="also write the markdown here (a '## Notes' section "
                                                "already in that file is kept below the new tables)")
    args = ap.parse_args()
    text = run(not args.no_baseline)
    print(text)
    if args.out:
        out = Path(args.out)
        old = out.read_text() if out.exists() else ""
        notes = old[old.index(NOTES_MARK):] if NOTES_MARK in old else ""
        out.write_text(text + ("\n" + notes if notes else ""))


if __name__ == "__main__":
    main()

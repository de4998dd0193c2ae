"""A search's Python against an older tree's, alternated image by image in one process (issue 37).

On a shared machine two runs of ``bench/pick.py`` minutes apart differ by more than a few per cent of
speed (the load moves); this bench runs both versions of the search's Python modules
(``vision/shape/``'s ``MODULES``: the search, its fits, scores, patch finish and verification; the
older ones read from git at ``REV``) on
the same renders (``bench/pick.py``'s, seed 8), in alternating order, and reports the median thread CPU
per image of each and the median of the per-image ratios. The compiled kernels and every other module are
the working tree's (shared by both: a change to them is not measured here, and an older search must call
them as it did). It also checks the two answer the same (matches' poses, scores and 1-sigmas, to the bit).

With ``--outcomes`` it reports instead what a search policy could skip: the working tree's least-squares fits
(level 1, level 0) and patch finishes per search by what became of them, with their thread CPU (a fit's
outcome is known only once it has run: the sum over the losers is what even a perfect policy could save),
on the renders (each searched twice) or, with ``--real``, on ``bench/pick_real.py``'s searches.

Run: ``.venv/bin/python bench/pick_ab.py REV [--n 40]``; ``.venv/bin/python bench/pick_ab.py --outcomes [--n 40]
[--real]``.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time
import types
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from numba.core.registry import CPUDispatcher as Dispatcher

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench import pick_real  # noqa: E402
from bench.pick import SIZE, make_scenes  # noqa: E402
from tests.support import pick_scenes  # noqa: E402
from vision import shape  # noqa: E402
from vision.shape import search  # noqa: E402

MODULES = ("uncertainty", "score", "responses", "patch", "verify", "refine", "tracking", "top_search", "search")
"""The modules compared (in import order); each old one sees the others' old versions (a module ``rev`` has
not, e.g. ``top_search`` before the search's top level moved there: none, ``rev``'s search has its job)."""


def old_find(rev: str) -> Callable[..., Any]:
    """``search.find`` of ``rev``'s ``MODULES`` (loaded under other names, each calling the others of ``rev``,
    the working tree's compiled kernels and the working tree's other modules)."""
    mods: dict[str, types.ModuleType] = {}
    for name in MODULES:
        path = f"vision/shape/{name}.py"
        shown = subprocess.run(["git", "show", f"{rev}:{path}"], cwd=ROOT, capture_output=True, text=True)
        if shown.returncode != 0 and name == "top_search":
            continue
        shown.check_returncode()
        src = shown.stdout
        mod = types.ModuleType(f"old_{name}")
        mod.__file__ = str(ROOT / path)
        sys.modules[mod.__name__] = mod  # dataclasses look their module up
        exec(compile(src, path, "exec"), mod.__dict__)
        mods[name] = mod
    for mod in mods.values():
        for attr, val in list(mod.__dict__.items()):
            if isinstance(val, Dispatcher):  # compiled kernels: the working tree's (cached, compiled once)
                setattr(mod, attr, getattr(sys.modules[f"vision.shape.{mod.__name__[4:]}"], attr, val))
                continue
            home = getattr(val, "__module__", None)
            if isinstance(home, str) and home.startswith("vision.shape.") and home[13:] in mods:
                setattr(mod, attr, getattr(mods[home[13:]], attr, val))
    find: Callable[..., Any] = mods["search"].find
    return find


def answers(res: Any) -> list[Any]:
    """Every field of the matches and the rejections, and the best rejected candidate (compared to the bit)."""
    return [repr(m) for m in res.matches] + [repr(r) for r in res.rejected] + [repr(res.best_rejected)]


class Paired:
    """A search that runs ``old`` and ``new`` on the same arguments, in alternating order (``k``: calls so far,
    its parity the order), records each one's thread CPU (ms; the first ``skip`` calls not) and whether they
    answer the same (``answers``), and returns ``new``'s result."""

    def __init__(self, old: Callable[..., Any], new: Callable[..., Any]) -> None:
        self.old, self.new = old, new
        self.t_old: list[float] = []
        self.t_new: list[float] = []
        self.same = True
        self.k = 0
        self.skip = 0

    def __call__(self, *a: Any, **kw: Any) -> Any:
        got: dict[bool, Any] = {}
        for f in ((self.old, self.new) if self.k % 2 == 0 else (self.new, self.old)):
            c = time.thread_time()
            got[f is self.old] = f(*a, **kw)
            if self.skip == 0:
                (self.t_old if f is self.old else self.t_new).append((time.thread_time() - c) * 1e3)
        self.k += 1
        self.skip = max(self.skip - 1, 0)
        self.same &= answers(got[True]) == answers(got[False])
        return got[False]


def outcomes(searches: Callable[[], object]) -> str:
    """The working tree's fits and finishes per search by outcome, with their thread CPU, over the searches
    ``searches()`` runs through ``vision.shape.find`` (the first one not counted: it loads the compiled
    kernels); the search's own functions are wrapped for the run and restored."""
    calls: list[tuple[int, Any, float]] = []  # (level, Refined, thread CPU s) of the current search
    count: dict[str, float] = {}
    cpu: dict[str, float] = {}
    total: list[float] = []
    first = [True]

    def add(key: str, dt: float) -> None:
        count[key] = count.get(key, 0.0) + 1
        cpu[key] = cpu.get(key, 0.0) + dt

    def timed(f: Callable[..., Any], after: Callable[[Any, float, Any, Any], None]) -> Callable[..., Any]:
        def call(*a: Any, **k: Any) -> Any:
            c = time.thread_time()
            r = f(*a, **k)
            after(r, time.thread_time() - c, a, k)
            return r
        return call

    def verified(got: Any, dt: float, a: Any, k: Any) -> None:
        hypotheses, sp = a[1], a[2]
        into = {id(r) for _, r in hypotheses}
        bar1 = 0.8 * min(sp.min_score, 0.5)  # search._refine_down's level-1 bar
        for lv, r, t in calls:
            if lv == 1:
                add("level 1: fails at its first association" if r.score <= 0 else
                    "level 1: below its bar" if r.score < bar1 else "level 1: reaches its bar", t)
            else:
                add("level 0: into the verification" if id(r) in into else
                    "level 0: below min_score" if r.score < sp.min_score else "level 0: suppressed at level 0", t)
        count["answered"] = count.get("answered", 0.0) + len(got[0])
        count["rejected by the verification"] = count.get("rejected by the verification", 0.0) + len(got[1])

    def found(got: Any, dt: float, a: Any, k: Any) -> None:
        calls.clear()
        if first:  # the first search (it loads the compiled kernels): not counted
            first.clear()
            count.clear()
            cpu.clear()
        else:
            total.append(dt * 1e3)

    saved = (search.refine_lsq, search._finish, search._verified, shape.find)
    search.refine_lsq = timed(saved[0], lambda r, dt, a, k: calls.append(
        (0 if k.get("fine") is not None else 1, r, dt)))
    search._finish = timed(saved[1], lambda r, dt, a, k: add("patch finish", dt))
    search._verified = timed(saved[2], verified)
    shape.find = timed(saved[3], found)  # type: ignore[assignment]
    try:
        searches()
    finally:
        search.refine_lsq, search._finish, search._verified, shape.find = saved  # type: ignore[assignment]
    n = len(total)
    mean = statistics.mean(total)
    rows = [f"{n} searches: thread CPU per search median {statistics.median(total):.2f} ms, mean {mean:.2f} ms",
            "| outcome | per search | thread CPU ms per search | of the mean |", "| --- | --- | --- | --- |"]
    for key in sorted(count):
        ms = cpu[key] / n * 1e3 if key in cpu else None
        share = "- | -" if ms is None else f"{ms:.3f} | {ms / mean:.1%}"
        rows.append(f"| {key} | {count[key] / n:.2f} | {share} |")
    return "\n".join(rows)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("rev", nargs="?", help="the older tree (a commit); not with --outcomes")
    ap.add_argument("--n", type=int, default=40, help="renders (bench/pick.py's, seed 8)")
    ap.add_argument("--outcomes", action="store_true", help="the working tree's fits by outcome instead")
    ap.add_argument("--real", action="store_true", help="bench/pick_real.py's searches instead of the renders")
    args = ap.parse_args()
    if (args.rev is None) != args.outcomes:
        ap.error("give either REV or --outcomes")
    load0 = os.getloadavg()[0]
    if args.real:
        print(outcomes(lambda: pick_real.run(False)) if args.outcomes else ab(args.rev, [], real=True))
    else:
        part = pick_scenes.part_bracket()
        teach_img, roi = pick_scenes.teach_scene(part, np.random.default_rng(1008), centre=(640.3, 480.6),
                                                 style=pick_scenes.SceneStyle(size=SIZE, noise_sigma=1.5, clutter=0))
        model = shape.teach(teach_img, roi)
        scenes = make_scenes(args.n, 8)
        imgs = [sc.img for _, sc in scenes]
        print(outcomes(lambda: [shape.find(model, img) for img in [imgs[0]] + imgs * 2]) if args.outcomes
              else ab(args.rev, [(model, img) for img in imgs], real=False))
    print(f"load average {load0:.1f} -> {os.getloadavg()[0]:.1f}")


def ab(rev: str, searches: list[tuple[Any, Any]], real: bool) -> str:
    """``rev``'s search against the working tree's, paired per search: on the renders' ``(model, image)``
    searches (twice each, the order flipped the second time) or, with ``real``, pick_real's."""
    old = old_find(rev)
    pair = Paired(old, search.find)
    if real:
        pair.skip = 1  # pick_real's first search loads the compiled kernels
        saved = shape.find
        shape.find = pair  # type: ignore[assignment]
        try:
            pick_real.run(False)
        finally:
            shape.find = saved  # type: ignore[assignment]
    else:
        for f in (old, search.find):
            f(*searches[0])
        for rep in range(2):
            for k, (model, img) in enumerate(searches):
                pair.k = k + rep
                pair(model, img)
    ratio = [b / a for a, b in zip(pair.t_old, pair.t_new, strict=True)]
    return (f"{rev} vs the working tree, {len(ratio)} searches each (thread CPU ms per search, median): "
            f"{statistics.median(pair.t_old):.2f} -> {statistics.median(pair.t_new):.2f} (mean "
            f"{statistics.mean(pair.t_old):.2f} -> {statistics.mean(pair.t_new):.2f}); paired ratio "
            f"{statistics.median(ratio):.3f}; same answers: {'yes' if pair.same else 'NO'}")


if __name__ == "__main__":
    main()

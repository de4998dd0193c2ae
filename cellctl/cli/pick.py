"""``cellctl pick teach|find``: teach a part model from an image ROI, find it in images.

``find`` with one ``--model`` answers ``[{"image", "matches": [{"u_px", "v_px", "angle_deg",
"score", "scores", ...}], "rejected": [...], "time_ms", "timed_out"[, "reason"]}]`` (docs/cli.md):
``scores`` are the verification's per match, ``rejected`` the candidates that reached the score and
failed it, with why; with several models it recognises which part each match is and adds ``part``,
``margin`` and ``runner_up`` to each match. ``time_ms``
is the in-process search time of that image (the compiled kernels are loaded once before the
first); ``reason`` says why nothing was found.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from cellctl.cli.output import CommandError
from cellctl.pick.model import COLOUR_MODES, REFINES, PartModel, colour_mode, takes_colour, teach
from vision import blob, shape
from vision.recognize import recognize
from vision.types import POLARITIES, SearchParams


def _roi(text: str | None, option: str) -> tuple[float, float, float, float] | None:
    """``U,V,W,H`` as four floats, or a one-line error naming the option."""
    if text is None:
        return None
    parts = text.replace(" ", "").split(",")
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        vals = []
    if len(vals) != 4 or not all(math.isfinite(v) for v in vals):
        raise CommandError(f"{option} must be U,V,W,H (four numbers, pixels), got {text!r}")
    return (vals[0], vals[1], vals[2], vals[3])


def read_image(path: str, colour: bool = False) -> NDArray[np.uint8]:
    """A grey image from a file (``colour``: as it is, B, G, R), or a one-line error naming the file."""
    p = Path(path)
    if not p.is_file():
        raise CommandError(f"image {path} does not exist")
    img = cv2.imread(str(p), cv2.IMREAD_COLOR if colour else cv2.IMREAD_GRAYSCALE)
    if img is None or img.size == 0:
        raise CommandError(f"cannot read image {path}: not an image file OpenCV can decode (PNG, BMP, TIFF, JPEG)")
    return np.asarray(img, dtype=np.uint8)


def _teach(args: argparse.Namespace) -> dict[str, Any]:
    if len(args.image) != len(args.roi):
        raise CommandError(f"give one --roi per --image (got {len(args.image)} images, {len(args.roi)} ROIs)")
    if len(args.image) > 1 and args.mode != "shape":
        raise CommandError("several teach images make a shape model: leave --mode blob out, or give one image")
    colour = colour_mode(args.mode, args.colour)
    if args.mode != "shape" and (colour != "grey" or args.refine is not None):
        raise CommandError("--colour and --refine make a shape model: leave --mode blob out")
    rois = [_roi(r, "--roi") for r in args.roi]
    name = args.name or Path(args.out_model).stem
    roi = rois[0]
    if roi is None:
        raise CommandError("--roi U,V,W,H is required to teach a part (the part's box in pixels)")
    params = shape.TeachParams(min_contrast=args.min_contrast, num_levels=args.num_levels, colour=colour)
    # a grey model is taught from the files' grey values exactly as before; a colour one from their colours
    imgs = [read_image(p, colour=colour != "grey") for p in args.image]
    views = [(i, r) for i, r in zip(imgs, rois, strict=True) if r is not None]
    if colour == "auto" and not takes_colour([i for i, _ in views], [r for _, r in views], params):
        imgs = [read_image(p) for p in args.image]
    more = [(img, r) for img, r in zip(imgs[1:], rois[1:], strict=True) if r is not None]
    # (several views: the edges seen in every image stay, vision.shape.multi)
    m = teach(imgs[0], roi, mode=args.mode, name=name, teach_image=str(args.image[0]), shape_params=params,
              blob_params=blob.BlobParams(threshold=args.threshold, polarity=args.polarity), more_views=more,
              refine=args.refine)
    m.save(args.out_model)
    return {"model": str(args.out_model), **m.summary()}


def _find(args: argparse.Namespace) -> list[dict[str, Any]]:
    models = [PartModel.load(p) for p in args.model]
    if args.max is not None and args.max < 1:
        raise CommandError("--max must be >= 1 (leave it out for all matches)")
    scale = (1.0, 1.0)
    if args.scale_range is not None:
        lo, _, hi = args.scale_range.partition(",")
        try:
            scale = (float(lo), float(hi))
        except ValueError:
            raise CommandError(f"--scale-range must be MIN,MAX (e.g. 0.9,1.1), got {args.scale_range!r}") from None
    sp = SearchParams(min_score=args.min_score, max_count=args.max,
                      angle_start_deg=args.angle_start, angle_extent_deg=args.angle_extent,
                      roi=_roi(args.search_roi, "--search-roi"),
                      timeout_s=None if args.timeout_ms is None else args.timeout_ms / 1000.0,
                      polarity=args.polarity, greediness=args.greediness, mirrored=args.mirrored,
                      scale_min=scale[0], scale_max=scale[1], min_surround=args.min_surround)
    out: list[dict[str, Any]] = []
    if any(m.shape is not None for m in models):
        shape.warm_up()  # once per process, so each image's time_ms is its own search
    # a model taught on a colour channel is searched in the colour image; grey models as before
    colour = any(m.shape is not None and m.shape.colour is not None for m in models)
    for path in args.images:
        img = read_image(path, colour=colour)
        for m in models:
            if (img.shape[1], img.shape[0]) != m.image_size and args.strict_size:
                raise CommandError(f"image {path} is {img.shape[1]}x{img.shape[0]}, model {m.name} was "
                                   f"taught on {m.image_size[0]}x{m.image_size[1]}")
        if len(models) == 1:
            res = models[0].find(img, sp)
            matches: list[dict[str, Any]] = [mt.as_dict() for mt in res.matches]
            timed_out, elapsed, reason = res.timed_out, res.elapsed_s, res.reason()
            rejected = [x.as_dict() for x in res.rejected]
        else:
            rr = recognize(models, img, sp)
            matches = [r.as_dict() for r in rr.matches]
            timed_out, elapsed, reason = rr.timed_out, rr.elapsed_s, rr.reason()
            rejected = [x.as_dict() for x in rr.rejected]
        item: dict[str, Any] = {"image": path, "matches": matches, "rejected": rejected, "timed_out": timed_out,
                                "time_ms": round(elapsed * 1000.0, 2)}
        if reason is not None:
            item["reason"] = reason
        out.append(item)
    return out


def register(sub: Any) -> None:
    parser: argparse.ArgumentParser = sub.add_parser("pick", help="teach part models and find parts")
    psub = parser.add_subparsers(dest="pick_command", metavar="ACTION", required=True)

    t = psub.add_parser("teach", help="a part model from the ROI of one image (or of 2-5 images of the part)")
    t.add_argument("--image", required=True, action="append",
                   help="the teach image; repeat (with one --roi each, in order) for 2-5 images of the same "
                        "part: the model keeps the edges seen in all of them")
    t.add_argument("--roi", required=True, metavar="U,V,W,H", action="append",
                   help="rectangle from (U,V) to (U+W,V+H) in pixels; its centre is the reference point")
    t.add_argument("--out", required=True, dest="out_model", help="model file to write (JSON)")
    t.add_argument("--mode", choices=("shape", "blob"), default="shape")
    t.add_argument("--name", help="part name (default: the model file's stem)")
    t.add_argument("--min-contrast", type=float, default=12.0, help="shape: least grey step of an edge")
    t.add_argument("--num-levels", type=int, default=0, help="shape: pyramid levels (0: automatic)")
    t.add_argument("--colour", choices=COLOUR_MODES, default=None,
                   help="shape: the channel of a colour image the model is made of: auto (default: chroma when "
                        "the part's colour edges are strong enough, else grey), grey (the grey value) or chroma "
                        "(the part's colour edges, the background's shading left out; colour images needed)")
    t.add_argument("--refine", choices=REFINES, default=None,
                   help="shape: rim: a round part (screw head, washer, bore) reports its rim's centre and its "
                        "1-sigma at every match; refused when the taught part is not round")
    t.add_argument("--threshold", type=float, default=None, help="blob: fixed grey threshold (default Otsu)")
    t.add_argument("--polarity", choices=("auto", "bright", "dark"), default="auto", help="blob: part polarity")
    t.set_defaults(func=_teach)

    f = psub.add_parser("find", help="instances of a part (or several parts) in images")
    f.add_argument("--model", required=True, action="append",
                   help="part model file; repeat to recognise several part types")
    f.add_argument("images", nargs="+", metavar="IMAGE")
    f.add_argument("--max", type=int, default=None, help="most matches per image (default: all)")
    f.add_argument("--min-score", type=float, default=0.5, help="least score 0..1 (default 0.5)")
    f.add_argument("--angle-start", type=float, default=-180.0, help="degrees (default -180)")
    f.add_argument("--angle-extent", type=float, default=360.0, help="degrees (default 360)")
    f.add_argument("--search-roi", default=None, metavar="U,V,W,H",
                   help="where the reference point may lie (default: the whole image)")
    f.add_argument("--polarity", choices=POLARITIES, default="ignore_local_polarity",
                   help="shape: use_polarity (edges as taught), ignore_global_polarity (or all reversed: "
                        "an inverted image), ignore_local_polarity (each edge either way; default)")
    f.add_argument("--mirrored", action="store_true", help="shape: also find the part's mirror image (face down)")
    f.add_argument("--scale-range", default=None, metavar="MIN,MAX",
                   help="shape: also search sizes MIN..MAX of the taught one (e.g. 0.9,1.1; default: 1,1)")
    f.add_argument("--greediness", type=float, default=0.9,
                   help="shape: 0 (safe, slower) .. 1 (fast, may miss weak parts); default 0.9")
    f.add_argument("--min-surround", type=float, default=0.2,
                   help="shape: how far the seen edges must enclose the part's centre (1: all round, ~0: a "
                        "half; default 0.2 refuses halves; -1: no check)")
    f.add_argument("--timeout-ms", type=float, default=None, help="answer with what was found so far")
    f.add_argument("--strict-size", action="store_true",
                   help="refuse images of another size than the teach image")
    f.add_argument("--out", dest="out_json", help="also write the JSON result to this file")
    f.set_defaults(func=_find)

"""``cellctl calib intrinsics``: camera calibration from images (or detections) of a planar target.

Prints the camera result (docs/cli.md ``cam.json``) on stdout, writes it with
``--out``, and prints each rejected view (with its reason), each verdict problem and a
cross-validation that cannot run (k too large for the usable views) on stderr. Exits 0 when the calibration itself
succeeded, even if the verdict says the data cannot support the model (``verdict.ok`` false);
non-zero with one clear line when it could not calibrate.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path
from typing import Any

from cellctl.cli.output import CommandError

log = logging.getLogger("cellctl.calib.intrinsics")

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff"}


def register(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "intrinsics", help="camera intrinsics from images of a planar target",
        description="Calibrate a camera (opencv5, opencv8 or division model) from images of a planar target. "
                    "IMAGE may be files or folders (their *.png/*.jpg/*.bmp/*.tif, in sorted name order).")
    p.add_argument("--target", required=True, help="target description YAML")
    p.add_argument("--model", default="opencv5", choices=["opencv5", "opencv8", "division", "fisheye4", "splined",
                                                     "auto"],
                   help="lens model; fisheye4: Kannala-Brandt, for wide and fisheye lenses; auto: the one that "
                        "cross-validates best (division, opencv5, fisheye4, opencv8, splined); splined: mrcal's "
                        "splined stereographic model, for lenses no parametric model fits (needs >= 40 views)")
    p.add_argument("--board-warp", choices=["auto", "on", "off"], default="auto",
                   help="solve a bowed target's two warp heights: auto (default) when cross-validation "
                        "prefers it, on, off")
    p.add_argument("--regularise", action="store_true",
                   help="solve opencv5/opencv8 regularised as mrcal does (distortion held near 0, opencv8's "
                        "rational k4-k6 harder, the principal point near the centre; ~0.25%% of the fit's cost); "
                        "--model auto also tries opencv8 regularised as a candidate")
    p.add_argument("images", nargs="*", metavar="IMAGE", help="image files or folders")
    p.add_argument("--detections", help="use detections JSON (output of cellctl detect) instead of images")
    p.add_argument("--out", dest="out_json", help="write the camera JSON (cam.json) here too")
    p.add_argument("--report", help="write an HTML report (residuals, coverage, distortion, uncertainty)")
    p.add_argument("--cross-validate", type=int, metavar="K", default=2,
                   help="k-fold cross-validation: projection difference between fold solutions over the covered "
                        "region (default 2: split-half; 0: off); the verdict uses it")
    p.add_argument("--cross-validate-repeats", metavar="R", default="auto",
                   help="partitions of the views the cross-validation draws (view i in fold i mod K, then seeded "
                        "random ones); it reports, chooses and judges by their median. auto (default): 3, then "
                        "more until the choice (or the median, for one model) is settled by the medians' 90%% "
                        "intervals, at most 8; a count R: exactly R")
    p.add_argument("--drop-outliers", action="store_true",
                   help="drop outlier views and points (the rule is in calibration/intrinsics/) and re-solve")
    p.add_argument("--reject-views", choices=["influence", "off"], default="influence",
                   help="influence (default): drop views whose leave-one-out effect on the projection is beyond "
                        "what the solve's uncertainty predicts (1%% false-alarm rate; a sheared or blurred view with "
                        "an ordinary RMS), keeping the image's corners and border covered; each is listed with "
                        "its reason; off: keep every view")
    p.add_argument("--export-opencv", metavar="F.yaml", help="also write OpenCV FileStorage YAML")
    p.add_argument("--export-ros", metavar="F.yaml", help="also write a ROS camera_info YAML")
    p.add_argument("--export-halcon", metavar="F.cal", help="also write HALCON camera parameters (division)")
    p.add_argument("--pixel-pitch-um", type=float, help="sensor cell width in micrometres (HALCON export)")
    p.set_defaults(func=run)


def _image_files(args: list[str]) -> list[Path]:
    files: list[Path] = []
    for a in args:
        p = Path(a)
        if p.is_dir():
            found = sorted(q for q in p.iterdir() if q.suffix.lower() in IMAGE_SUFFIXES)
            if not found:
                raise CommandError(f"{p}: folder holds no *.png/*.jpg/*.bmp/*.tif images")
            files += found
        elif p.is_file():
            files.append(p)
        else:
            raise CommandError(f"{p}: no such image file or folder")
    return files


def _detections(args: argparse.Namespace, target: Any) -> list[Any]:
    from calibration.observations import Detection

    if args.detections:
        expected = "give the JSON list that `cellctl detect --out F.json` writes"
        try:
            data = json.loads(Path(args.detections).read_text())
        except OSError as exc:
            raise CommandError(f"{args.detections}: cannot read detections ({exc.strerror})") from exc
        except UnicodeDecodeError:
            raise CommandError(f"{args.detections}: not a text file (binary data); {expected}") from None
        except json.JSONDecodeError as exc:
            raise CommandError(f"{args.detections}: not valid JSON ({exc}); {expected}") from exc
        if not isinstance(data, list):
            kind = "object" if isinstance(data, dict) else "string" if isinstance(data, str) else "number or literal"
            raise CommandError(f"{args.detections}: holds a JSON {kind}, not a list of detections; {expected}")
        if not all(isinstance(d, dict) for d in data):
            raise CommandError(f"{args.detections}: a list whose entries are not detections; {expected}")
        try:
            return [Detection.from_json(d) for d in data]
        except (KeyError, TypeError, ValueError) as exc:
            raise CommandError(f"{args.detections}: not a cellctl detect JSON list ({exc}); {expected}") from exc
    if not args.images:
        raise CommandError("give IMAGE files or folders (or --detections FILE)")
    try:
        from calibration.detect import detect_file
    except ImportError as exc:  # pragma: no cover - detection ships with the package
        raise CommandError(f"target detection is not available ({exc})") from exc
    out = []
    files = _image_files(args.images)
    for k, f in enumerate(files):
        d = detect_file(f, target)
        log.info("[%d/%d] %s: %s", k + 1, len(files), f.name,
                 f"{len(d.ids)} points" if d.found else f"not found ({d.reason})")
        out.append(d)
    return out


def run(args: argparse.Namespace) -> dict[str, Any]:
    from calibration.targets import load_target

    if args.cross_validate and args.cross_validate < 2:
        raise CommandError("--cross-validate K needs K >= 2")
    if args.cross_validate_repeats != "auto":
        try:
            args.cross_validate_repeats = int(args.cross_validate_repeats)
        except ValueError:
            raise CommandError(f"--cross-validate-repeats R needs a count R >= 1 or auto, not "
                               f"{args.cross_validate_repeats!r}") from None
        if args.cross_validate_repeats < 1:
            raise CommandError("--cross-validate-repeats R needs R >= 1")
    if args.model == "auto" and not args.cross_validate:
        raise CommandError("--model auto chooses by cross-validation: give --cross-validate K >= 2")
    if args.export_halcon and args.model != "division":
        raise CommandError("--export-halcon needs --model division (HALCON's area_scan_division)")
    if args.export_halcon and not args.pixel_pitch_um:
        raise CommandError("--export-halcon needs --pixel-pitch-um (the sensor cell width, e.g. 3.45)")
    if (args.export_opencv or args.export_ros) and args.model in ("division", "fisheye4", "splined"):
        raise CommandError(f"OpenCV/ROS files cannot express the {args.model} model"
                           + ("; use --export-halcon" if args.model == "division" else "; keep the cam.json"))
    target = load_target(args.target)
    dets = _detections(args, target)
    res, selection, cv = _calibrate(args, dets, target)
    if cv is not None and "error" not in cv:
        from calibration.verdict import cross_validation_problem

        prob = cross_validation_problem(cv)
        if prob:
            res.verdict["problems"].append(prob)
            res.verdict["ok"] = False
    out = res.to_json()
    out["target"] = target.describe()
    if selection is not None:
        out["model_selection"] = {k: v for k, v in selection.items() if k != "cross_validation"}
    for rej in out["rejected_views"]:
        print(f"cellctl: view rejected: {rej['image']}: {rej['reason']}", file=sys.stderr)
    if cv is not None:
        out["cross_validation"] = cv
    _exports(args, res.camera)
    if args.report:
        from calibration.report import write_report

        cv = out.get("cross_validation")
        if cv and "error" not in cv and selection is not None:
            cv = {**cv, "model_selection": out["model_selection"]}
        write_report(res, args.report, cross_validation=cv if cv and "error" not in cv else None,
                     image_files=_image_files(args.images) if args.images else None)
        log.info("report written to %s", args.report)
    for prob in res.verdict["problems"]:
        print(f"cellctl: verdict: {prob['code']}: {prob['message']}", file=sys.stderr)
    if not res.verdict["ok"]:
        # The result is written all the same (stdout, --out), then exit 3 as `job run --follow` does.
        from cellctl.cli.job import VERDICT_NOT_OK_EXIT
        from cellctl.cli.output import emit

        emit(out, args.out_json)
        raise CommandError("verdict NOT OK: the data cannot support this calibration (see verdict.problems); "
                           "the result is written", exit_code=VERDICT_NOT_OK_EXIT)
    return out


def _candidates(args: argparse.Namespace) -> list[tuple[str, bool, bool]]:
    """(model, board warp, regularised) to choose from, simplest first. ``--model auto`` tries opencv8
    regularised (mrcal's solve: its rational terms held near 0) before opencv8 free."""
    reg = bool(getattr(args, "regularise", False))
    if args.model != "auto":
        models = [(args.model, reg)]
    elif args.export_opencv or args.export_ros:
        models = [("opencv5", reg), ("opencv8", True), ("opencv8", False)]   # what those files can express
    else:
        models = [("division", False), ("opencv5", reg), ("fisheye4", False), ("opencv8", True), ("opencv8", False),
                  ("splined", False)]
    warps = {"auto": [False, True], "on": [True], "off": [False]}[args.board_warp]
    # auto does not try the splined model with the warp (another minute of CPU on a large set);
    # --board-warp on solves it
    return [(m, w, r) for m, r in models for w in warps
            if not (m == "splined" and w and args.board_warp == "auto")] or [(m, False, r) for m, r in models]


def _calibrate(args: argparse.Namespace, dets: list[Any], target: Any
               ) -> tuple[Any, dict[str, Any] | None, dict[str, Any] | None]:
    """The calibration, the model selection (None when there was nothing to choose) and the
    cross-validation block (None when not asked; ``{"k", "error"}`` when it could not run)."""
    from calibration import intrinsics

    cands = _candidates(args)
    k = args.cross_validate
    repeats = args.cross_validate_repeats
    reject = args.reject_views == "influence"
    if k and len(cands) > 1:
        try:
            res, selection = intrinsics.select_by_cross_validation(dets, target, cands, k,
                                                                   drop_outliers=args.drop_outliers,
                                                                   reject_views=reject, repeats=repeats)
            log.info("model chosen by cross-validation: %s", selection["chosen"])
            return res, selection, selection["cross_validation"]
        except intrinsics.CrossValidationError:
            pass   # not enough views to choose: the first candidate, and the reason below
    model, warp, reg = cands[0]
    try:
        res = intrinsics.calibrate(dets, target, model, drop_outliers=args.drop_outliers, board_warp=warp,
                                   reject_views=reject and model != "splined", regularise=reg)
    except intrinsics.IntrinsicsError as exc:
        raise CommandError(f"calibration failed: {exc}") from exc
    if not k:
        return res, None, None
    try:
        cv = intrinsics.cross_validate(dets, target, model, k, drop_outliers=args.drop_outliers, full=res,
                                       board_warp=warp, repeats=repeats, regularise=reg)
    except intrinsics.CrossValidationError as exc:
        # The calibration stands; only the cross-validation cannot run as asked.
        cv = {"k": k, "error": str(exc)}
        print(f"cellctl: cross-validation not run: {exc}", file=sys.stderr)
    return res, None, cv


def _exports(args: argparse.Namespace, camera: Any) -> None:
    from calibration import io as cal_io

    if args.export_opencv:
        cal_io.write_opencv_yaml(camera, args.export_opencv)
    if args.export_ros:
        cal_io.write_ros_yaml(camera, args.export_ros)
    if args.export_halcon:
        Path(args.export_halcon).write_text(cal_io.halcon_cam_par(camera, args.pixel_pitch_um * 1e-6))

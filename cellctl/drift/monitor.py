"""The drift monitor of a cell: checks, the chart of the active calibration, the alarm, the re-solve.

One :class:`DriftMonitor` per service (``Services.drift``, made when ``drift:`` is configured). A
check measures the fiducials in a frame (``cellctl.drift.fiducials``) against the active hand-eye
(``calibration.drift.measure``; a camera on the arm through the robot's pose at the picture), judges
``drift_mm`` on that calibration's I-MR chart (``calibration.drift.Chart``: the first
``baseline_checks`` set its limits; the chart is rebuilt from the store after a restart) and stores
the record. Frames come from production (every
``every_cycles``-th picture, checked on the run's store thread: no extra picture, no extra motion),
from the idle thread (every ``every_s`` while no production run uses the camera) or on request.

An alarm (a check breaking a Western Electric rule) is written to the audit, shown by ``/metrics``,
the Modbus STATUS bit 6 and OPC UA, and, with ``pause_on_alarm``, pauses the run after its cycle.
The cell's state is that of its last judged check; a new active calibration starts a new chart.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from numpy.typing import NDArray

from calibration import geometry as g
from calibration.camera_model import CameraModel
from calibration.drift import Chart, Limits
from calibration.drift.fiducials import FiducialError, measure, resolve
from cellctl.drift.config import DriftConfig
from cellctl.drift.fiducials import observe
from cellctl.errors import CellctlError
from cellctl.mapping import ActiveMapping, NoCalibration, active_mapping

if TYPE_CHECKING:
    from cellctl.services import Services

log = logging.getLogger(__name__)

State = Literal["off", "no_calibration", "baseline", "ok", "alarm"]
Source = Literal["production", "idle", "request"]
HISTORY = 200
"""Records ``GET /drift`` shows (the store keeps all)."""


class DriftUnavailable(CellctlError, ValueError):
    """No check can be made now (no active hand-eye, fiducials not seen); the message says why."""


class DriftMonitor:
    """Drift checks of the cell's fixed camera (thread-safe)."""

    def __init__(self, services: Services, cfg: DriftConfig) -> None:
        self.services, self.cfg = services, cfg
        self.camera_id, self.robot_id = cfg.ids(services.config.calibration)
        self._lock = threading.Lock()
        self._check_lock = threading.Lock()
        """One check at a time (a chart judges its points in order)."""
        self._chart: Chart | None = None
        self._chart_calibration: int | None = None
        self._state: State = "baseline"
        self._last: dict[str, Any] | None = None
        self._pictures: dict[int, int] = {}
        """Production pictures seen per run id."""
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # -- life -----------------------------------------------------------------------------------------
    def start(self) -> None:
        """Start the idle checks (every ``every_s``; none when 0)."""
        if self.cfg.every_s > 0 and self._thread is None:
            self._thread = threading.Thread(target=self._idle, name="drift-idle", daemon=True)
            self._thread.start()

    def close(self) -> None:
        """Stop the idle checks; a check in progress finishes (its grab is bounded)."""
        self._stop.set()
        thread, self._thread = self._thread, None
        if thread is not None:
            thread.join(30.0)
            if thread.is_alive():
                log.warning("the drift idle thread has not ended in 30 s")

    def _idle(self) -> None:
        while not self._stop.wait(self.cfg.every_s):
            if self._busy():
                continue
            try:
                self.check_now("system", "idle")
            except DriftUnavailable as exc:
                log.info("drift idle check skipped: %s", exc)
            except Exception:  # noqa: BLE001 - the idle checks go on; the next may work
                log.exception("drift idle check failed")

    def _busy(self) -> bool:
        """Not idle: a production run uses the camera, a routine runs, or something owns the robot's motion."""
        manager = self.services.production_if_made
        if manager is not None and any(r.s.camera_id == self.camera_id for r in manager.running()):
            return True
        if any(j.state == "running" for j in self.services.jobs.list()):
            return True
        slot = self.services.cell.robots.get(self.robot_id)
        return slot is not None and bool(slot.device.motion.status().get("owner"))

    # -- checks ---------------------------------------------------------------------------------------
    def _mapping(self) -> tuple[ActiveMapping, CameraModel]:
        """The active hand-eye and the camera it maps through."""
        try:
            m = active_mapping(self.services, self.camera_id, self.robot_id, "handeye", True)
        except NoCalibration as exc:
            raise DriftUnavailable(f"no drift check: {exc}") from None
        if m.camera is None:
            raise DriftUnavailable(f"no drift check: the active hand-eye of {self.camera_id}/{self.robot_id} has no "
                                   "camera to map through: activate the camera's intrinsics")
        return m, m.camera

    def _T_base_cam(self, mapping: ActiveMapping, T_base_tool: NDArray[np.float64] | None) -> NDArray[np.float64]:
        """Where the calibration puts the camera: fixed (eye-to-hand), or on the arm at ``T_base_tool``."""
        if mapping.calib.get("setup") == "eye-in-hand":
            if T_base_tool is None:
                raise DriftUnavailable("no drift check: a camera on the arm needs the robot's pose at the picture")
            return np.asarray(T_base_tool, dtype=np.float64) @ np.asarray(mapping.calib["T_tool_cam"], dtype=np.float64)
        return np.asarray(mapping.calib["T_base_cam"], dtype=np.float64)

    def _robot_pose(self, mapping: ActiveMapping) -> NDArray[np.float64] | None:
        """The robot's pose now when the camera rides on the arm (it sees from there); None for a fixed camera."""
        if mapping.calib.get("setup") != "eye-in-hand":
            return None
        return np.asarray(self.services.cell.robot(self.robot_id).ensure_open().state().T_base_tool)

    def check_now(self, who: str, source: Source = "request") -> dict[str, Any]:
        """Grab a frame from the camera and check it (a camera on the arm: from where the robot stands)."""
        T_base_tool = self._robot_pose(self._mapping()[0])
        frame = self.services.cell.camera(self.camera_id).ensure_open().grab(timeout_s=5.0)
        return self.check_pixels(frame.pixels, source, who, T_base_tool)

    def on_production_picture(self, run: Any, frame_id: int | None, camera_id: str,
                              later: Callable[[Callable[[], None]], None]) -> None:
        """A production run took a picture: every ``every_cycles``-th is checked, through ``later`` (the run's
        store thread: off the cycle's path); an alarm with ``pause_on_alarm`` pauses ``run``."""
        n_every = self.cfg.every_cycles
        if n_every <= 0 or frame_id is None or camera_id != self.camera_id:
            return
        run_id = int(run.status.run_id)
        with self._lock:
            n = self._pictures[run_id] = self._pictures.get(run_id, 0) + 1
        if n % n_every:
            return
        try:
            pixels = self.services.frames.get(int(frame_id)).pixels
        except KeyError:
            return
        # A camera on the arm took the picture from the capture pose, where the arm still stands (a fixed
        # camera's check does not use it).
        T_base_tool = np.asarray(run.robot.state().T_base_tool)

        def check() -> None:
            try:
                rec = self.check_pixels(pixels, "production", "system", T_base_tool)
            except DriftUnavailable as exc:
                log.info("drift check on production picture skipped: %s", exc)
                return
            except Exception:  # noqa: BLE001 - a failed check must not fail the run
                log.exception("drift check on a production picture failed")
                return
            if rec["state"] == "alarm" and self.cfg.pause_on_alarm:
                log.warning("drift alarm (%s): pausing production run %s after its cycle", rec["rule"], run_id)
                run.pause()

        later(check)

    def check_pixels(self, pixels: NDArray[Any], source: Source, who: str,
                     T_base_tool: NDArray[np.float64] | None = None) -> dict[str, Any]:
        """Check one frame (a camera on the arm: taken at ``T_base_tool``): the stored record (``state``:
        baseline, ok, alarm, or failed when the fiducials were not seen: then the drift values are null and
        ``reason`` says why)."""
        with self._check_lock:
            mapping, camera = self._mapping()
            T_base_cam = self._T_base_cam(mapping, T_base_tool)
            chart = self._chart_for(mapping.calibration_id)
            X, uv = observe(self.cfg, self.services.config.targets, pixels, camera, T_base_cam)
            rec: dict[str, Any] = {"t": time.time(), "source": source, "calibration_id": mapping.calibration_id}
            try:
                m = measure(camera, T_base_cam, uv, X)
            except FiducialError as exc:
                rec.update({"drift_px": None, "drift_mm": None, "drift_deg": None, "state": "failed", "rule": None,
                            "reason": str(exc), "seen": int(np.all(np.isfinite(uv), axis=1).sum())})
            else:
                state, rule = chart.add(m.drift_mm)
                rec.update({"drift_px": _r(m.drift_px), "drift_mm": _r(m.drift_mm), "drift_deg": _r(m.drift_deg),
                            "state": state, "rule": rule, "sigma_mm": _r(m.sigma_mm),
                            "sigma_deg": None if m.sigma_deg is None else _r(m.sigma_deg), "seen": m.seen})
            rec["id"] = self.services.store.add_drift_check(self.camera_id, mapping.calibration_id, rec)
            self._judged(rec, who)
            return rec

    def _judged(self, rec: dict[str, Any], who: str) -> None:
        if rec["state"] == "failed":
            return
        with self._lock:
            was, self._state, self._last = self._state, rec["state"], rec
        self.services.metrics.observe_drift(self.camera_id, float(rec["drift_mm"]), rec["state"] == "alarm")
        if rec["state"] == "alarm" and was != "alarm":
            log.warning("drift alarm on %s: %s (drift %.3f mm, %.4f deg)", self.camera_id, rec["rule"],
                        rec["drift_mm"], rec["drift_deg"])
            self.services.store.audit(who, "drift.alarm", f"camera:{self.camera_id}",
                                      {k: rec.get(k) for k in ("drift_px", "drift_mm", "drift_deg", "rule", "id",
                                                               "calibration_id", "source")}, "alarm")
        elif was == "alarm" and rec["state"] != "alarm":
            self.services.store.audit(who, "drift.clear", f"camera:{self.camera_id}",
                                      {"drift_mm": rec["drift_mm"], "id": rec["id"]}, rec["state"])

    def _chart_for(self, calibration_id: int) -> Chart:
        """The chart of ``calibration_id`` (rebuilt from its stored checks when it is not the one in memory)."""
        if self._chart is not None and self._chart_calibration == calibration_id:
            return self._chart
        chart = Chart(self.cfg.baseline_checks, self.cfg.min_sigma_mm)
        last: dict[str, Any] | None = None
        for rec in self.services.store.drift_checks(self.camera_id, 10_000, calibration_id):
            if rec.get("drift_mm") is not None:
                chart.add(float(rec["drift_mm"]))
                last = rec
        with self._lock:
            self._chart, self._chart_calibration = chart, calibration_id
            self._last = last
            self._state = "baseline" if last is None else last["state"]
        # After a restart the front ends show the stored state at once; a new calibration clears the alarm.
        self.services.metrics.observe_drift(self.camera_id, None if last is None else float(last["drift_mm"]),
                                            last is not None and last["state"] == "alarm")
        return chart

    # -- what the front ends show --------------------------------------------------------------------
    @property
    def alarm(self) -> bool:
        """The last judged check raised an alarm (no I/O: safe on an event loop)."""
        with self._lock:
            return self._state == "alarm"

    def last(self) -> dict[str, Any] | None:
        with self._lock:
            return None if self._last is None else dict(self._last)

    def state(self) -> State:
        """The cell's drift state now (reads the active calibration: not on an event loop)."""
        try:
            mapping, _ = self._mapping()
        except DriftUnavailable:
            return "no_calibration"
        self._chart_for(mapping.calibration_id)
        with self._lock:
            return self._state

    def public(self, limit: int = HISTORY) -> dict[str, Any]:
        """``GET /drift``: the state, the records (oldest first) and the chart's limits (each null in the baseline)."""
        state = self.state()
        with self._lock:
            chart, cal = self._chart, self._chart_calibration
        lim = None if chart is None else chart.lim
        records = self.services.store.drift_checks(self.camera_id, limit)
        return {"state": state, "camera_id": self.camera_id, "calibration_id": cal, "records": records,
                "limits": limits_json(lim),
                "baseline_checks": self.cfg.baseline_checks, "every_cycles": self.cfg.every_cycles,
                "every_s": self.cfg.every_s, "pause_on_alarm": self.cfg.pause_on_alarm}

    # -- the re-solve ---------------------------------------------------------------------------------
    def resolve(self, who: str) -> dict[str, Any]:
        """Re-solve the camera's pose from the fiducials in a fresh frame (the intrinsics and the robot side
        kept) and store it as a new hand-eye version, not activated: ``{"calibration_id", "verdict",
        "shift_mm", "shift_deg"}``."""
        mapping, camera = self._mapping()
        on_arm = mapping.calib.get("setup") == "eye-in-hand"
        T_base_tool = self._robot_pose(mapping)
        frame = self.services.cell.camera(self.camera_id).ensure_open().grab(timeout_s=5.0)
        T_old = self._T_base_cam(mapping, T_base_tool)
        X, uv = observe(self.cfg, self.services.config.targets, frame.pixels, camera, T_old)
        try:
            r = resolve(camera, T_old, uv, X)
        except FiducialError as exc:
            raise DriftUnavailable(f"no re-solve: {exc}") from None
        # A camera on the arm: the re-solved pose through the robot's pose at the picture (T_tool_cam).
        key, T_new = (("T_tool_cam", g.invert(T_base_tool) @ r.T_base_cam) if on_arm and T_base_tool is not None
                      else ("T_base_cam", r.T_base_cam))
        problems = []
        if r.rms_px > self.cfg.resolve_max_rms_px:
            problems.append({"code": "fiducials_fit", "message": f"the fiducials fit the re-solved camera with "
                             f"{r.rms_px:.3f} px RMS (more than {self.cfg.resolve_max_rms_px:g} px): a mark moved or "
                             "was misread; check the fiducials"})
        history = [{k: h.get(k) for k in ("t", "drift_mm", "drift_deg", "state", "rule")}
                   for h in self.services.store.drift_checks(self.camera_id, 60, mapping.calibration_id)]
        verdict = {"ok": not problems, "problems": problems,
                   "rms_px": _r(r.rms_px), "fiducials_seen": r.seen}
        result = {**mapping.calib, key: T_new.tolist(), "verdict": verdict,
                  "drift_resolve": {"from_calibration_id": mapping.calibration_id, "shift_mm": _r(r.shift_mm),
                                    "shift_deg": _r(r.shift_deg), "rms_px": _r(r.rms_px),
                                    "sigma_trans_mm": _r(r.sigma_trans_mm), "sigma_rot_deg": _r(r.sigma_rot_deg),
                                    "fiducials_seen": r.seen, "t": time.time(), "history": history}}
        unc = result.get("uncertainty")
        if isinstance(unc, dict):  # the pose's own covariance (rotation, translation), as the solver gives it
            result["uncertainty"] = {**unc, "source": "drift re-solve (fiducials)"}
        rec = self.services.store.save_calibration(
            "handeye", self.camera_id, self.robot_id, result,
            {"drift_resolve": {"uv_px": np.where(np.isfinite(uv), uv, -1.0).tolist(), "points_base_m": X.tolist(),
                               "from_calibration_id": mapping.calibration_id,
                               "T_base_tool": None if T_base_tool is None else T_base_tool.tolist()}},
            creator=who, note=f"drift re-solve of calibration {mapping.calibration_id}: camera moved "
                              f"{r.shift_mm:.3f} mm, turned {r.shift_deg:.4f} deg")
        self.services.store.audit(who, "drift.resolve", f"calibration:{rec.id}",
                                  {"from_calibration_id": mapping.calibration_id, "shift_mm": _r(r.shift_mm),
                                   "shift_deg": _r(r.shift_deg), "verdict_ok": verdict["ok"]}, "stored (not active)")
        return {"calibration_id": rec.id, "verdict": verdict, "shift_mm": _r(r.shift_mm),
                "shift_deg": _r(r.shift_deg), key: T_new.tolist(),
                f"{key}_ur": [float(v) for v in g.transform_to_ur_pose(T_new)]}


def limits_json(lim: Limits | None) -> dict[str, Any]:
    """The chart's limits for ``GET /drift`` (mm; each null while the baseline is being set)."""
    if lim is None:
        return dict.fromkeys(("center_mm", "ucl_mm", "lcl_mm", "mr_ucl_mm", "sigma_mm", "baseline_checks"))
    return {"center_mm": _r(lim.center), "ucl_mm": _r(lim.ucl), "lcl_mm": _r(lim.lcl), "mr_ucl_mm": _r(lim.mr_ucl),
            "sigma_mm": _r(lim.sigma), "baseline_checks": lim.n}


def _r(v: float) -> float:
    return round(float(v), 6)

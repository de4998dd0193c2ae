"""Prometheus metrics of a running cell (``GET /metrics``), one registry per service instance.

What is measured, and where it comes from:

- ``cellctl_http_request_duration_seconds{method,route,status}`` (histogram): every HTTP request,
  timed by ``cellctl.api.middleware.RequestMiddleware``, labelled with the route *template*
  (``/robots/{robot_id}/state``, never the raw path, so scanners cannot blow up the series count;
  paths no route matches are ``route="unmatched"``).
- ``cellctl_pick_latency_seconds`` (histogram), ``cellctl_pick_match_score`` (histogram of every
  match's score) and ``cellctl_picks_total{result="found"|"none"}``: fed by ``observe_pick``, which
  whatever runs a pick (REST route, PLC front ends) calls.
- ``cellctl_routine_outcomes_total{routine,state}``: every finished job (succeeded / failed /
  cancelled), fed by ``cellctl.jobs.JobManager`` through ``routine_finished``.
- ``cellctl_drift_mm{camera}`` and ``cellctl_drift_alarm{camera}`` (gauges): the last judged drift
  check (``cellctl.drift``), fed by ``observe_drift``.
- Read from the live cell at each scrape: ``cellctl_device_available{category,device,kind}``,
  ``cellctl_device_outages_total{category,device}``, ``cellctl_robot_connected{robot}`` (1 when the
  robot's slot is open and its adapter reports fresh state), and per camera, when its adapter counts
  them, ``cellctl_camera_frames_total``, ``cellctl_camera_lost_frames_total``,
  ``cellctl_camera_incomplete_frames_total`` (adapter ``health()``), and
  ``cellctl_camera_frame_rate_hz`` (the acquisition rate the camera reports in ``settings()``). The
  measured frame rate is ``rate(cellctl_camera_frames_total[1m])`` in PromQL.

Each service has its own ``CellMetrics`` (a typed field of ``cellctl.services.Services``) in its own
``CollectorRegistry`` (not prometheus_client's global one), so several apps in one process never
collide; nothing is registered at module level. The pick flow records through
``services.metrics.observe_pick``, the ``JobManager`` through the metrics its ``Services`` gave it.
They never raise: a metric must not break a pick or a routine. After ``detach`` (the service's
close) they record nothing and the scrape reads no cell; the registry keeps its counts.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Iterable, Iterator
from typing import TYPE_CHECKING, Any, Protocol

from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, Counter, Gauge, Histogram, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.registry import Collector

from cellctl import __version__
from drivers.health import DeviceHealth, Monitored

if TYPE_CHECKING:
    from cellctl.cell import Cell, DeviceSlot

log = logging.getLogger(__name__)

CONTENT_TYPE = CONTENT_TYPE_LATEST
REQUEST_BUCKETS_S = (0.002, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0)
PICK_BUCKETS_S = (0.01, 0.025, 0.05, 0.1, 0.2, 0.3, 0.5, 0.75, 1.0, 2.0, 5.0)
SCORE_BUCKETS = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.85, 0.9, 0.95, 1.0)
SETTINGS_TIMEOUT_S = 0.5
"""A camera's ``settings()`` may ask the device; a scrape waits this long for it, then skips it."""


class CellMetrics:
    """All metrics of one service instance, in its own registry."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry(auto_describe=True)
        r = self.registry
        self.request_duration = Histogram(
            "cellctl_http_request_duration_seconds", "HTTP request latency, by route template and status",
            ["method", "route", "status"], buckets=REQUEST_BUCKETS_S, registry=r)
        self.pick_latency = Histogram("cellctl_pick_latency_seconds", "time from pick request to result",
                                      buckets=PICK_BUCKETS_S, registry=r)
        self.match_score = Histogram("cellctl_pick_match_score", "score of each match a pick returned",
                                     buckets=SCORE_BUCKETS, registry=r)
        self.picks = Counter("cellctl_picks", "picks, by whether anything was found", ["result"], registry=r)
        self.routines = Counter("cellctl_routine_outcomes", "finished routines (jobs), by routine and final state",
                                ["routine", "state"], registry=r)
        self.drift_mm = Gauge("cellctl_drift_mm", "the last drift check's drift at the fiducials, mm "
                              "(docs/drift.md)", ["camera"], registry=r)
        self.drift_alarm = Gauge("cellctl_drift_alarm", "1 when the last drift check raised an alarm",
                                 ["camera"], registry=r)
        info = Gauge("cellctl_build_info", "the running cellctl version (value 1)", ["version"], registry=r)
        info.labels(__version__).set(1)
        self.devices = DeviceCollector()
        r.register(self.devices)
        self.attached = True
        """False after ``detach``: nothing more is recorded."""

    def attach(self, cell: Cell | None) -> None:
        """Read ``cell``'s devices at each scrape and record again (the service's start)."""
        self.devices.cell = cell
        self.attached = True

    def detach(self) -> None:
        """Forget the cell and record nothing more (the service's close); the registry keeps its counts.
        A camera's ``settings()`` still being asked is waited for (``SETTINGS_TIMEOUT_S`` each)."""
        self.devices.cell = None
        self.attached = False
        self.devices.join(SETTINGS_TIMEOUT_S)

    def observe_request(self, method: str, route: str, status: int, duration_s: float) -> None:
        self.request_duration.labels(method, route, str(status)).observe(duration_s)

    def observe_pick(self, latency_s: float, scores: Iterable[float]) -> None:
        """One pick: its latency (seconds) and the scores of the matches it returned (may be none); never raises."""
        if not self.attached:
            return
        try:
            self.pick_latency.observe(float(latency_s))
            n = 0
            for s in scores:
                self.match_score.observe(float(s))
                n += 1
            self.picks.labels("found" if n else "none").inc()
        except Exception:  # noqa: BLE001 - metrics never break a pick
            log.debug("observe_pick failed", exc_info=True)

    def routine_finished(self, routine: str, state: str) -> None:
        """A finished routine (job) and its final state; never raises."""
        if not self.attached:
            return
        try:
            self.routines.labels(routine, state).inc()
        except Exception:  # noqa: BLE001 - metrics never break a job
            log.debug("routine_finished failed", exc_info=True)

    def observe_drift(self, camera: str, drift_mm: float | None, alarm: bool) -> None:
        """A judged drift check of ``camera`` (mm, alarm or not; ``drift_mm`` None: no check yet, the last
        value stays); never raises."""
        if not self.attached:
            return
        try:
            if drift_mm is not None:
                self.drift_mm.labels(camera).set(float(drift_mm))
            self.drift_alarm.labels(camera).set(1.0 if alarm else 0.0)
        except Exception:  # noqa: BLE001 - metrics never break a check
            log.debug("observe_drift failed", exc_info=True)

    def render(self) -> bytes:
        """The registry in Prometheus' text exposition format."""
        return generate_latest(self.registry)


class DeviceCollector(Collector):
    """Reads the cell's device slots at each scrape (nothing is cached between scrapes)."""

    def __init__(self) -> None:
        self.cell: Cell | None = None
        self._pending: dict[str, threading.Thread] = {}
        self._lock = threading.Lock()

    def join(self, timeout_s: float) -> None:
        """Wait for the ``settings()`` calls in progress (each thread is bounded by its device's answer: a
        device that hangs keeps its one thread, never more, and it is logged)."""
        with self._lock:
            pending = list(self._pending.values())
            self._pending.clear()
        for thread in pending:
            thread.join(timeout_s)
            if thread.is_alive():
                log.warning("%s: the camera's settings() call has not returned; its thread stays", thread.name)

    def describe(self) -> Iterable[Metric]:
        return []  # the series depend on the cell; describe nothing so registration never scrapes

    def collect(self) -> Iterator[Metric]:
        cell = self.cell
        available = GaugeMetricFamily("cellctl_device_available", "1 when the device is open and answering",
                                      labels=["category", "device", "kind"])
        outages = CounterMetricFamily("cellctl_device_outages", "times the device was lost (service or adapter "
                                      "count, whichever is higher)", labels=["category", "device"])
        connected = GaugeMetricFamily("cellctl_robot_connected", "1 when the robot is connected with fresh state",
                                      labels=["robot"])
        frames = CounterMetricFamily("cellctl_camera_frames", "frames the camera adapter received",
                                     labels=["camera"])
        lost = CounterMetricFamily("cellctl_camera_lost_frames", "frames the camera sent that never arrived",
                                   labels=["camera"])
        incomplete = CounterMetricFamily("cellctl_camera_incomplete_frames", "frames that arrived incomplete",
                                         labels=["camera"])
        rate = GaugeMetricFamily("cellctl_camera_frame_rate_hz", "acquisition frame rate the camera reports",
                                 labels=["camera"])
        if cell is not None:
            for category, slots in (("camera", cell.cameras), ("robot", cell.robots), ("io", cell.io)):
                for device_id, slot in slots.items():
                    health = _health(slot)
                    up = bool(slot.is_open and (health is None or health.available))
                    available.add_metric([category, device_id, slot.kind], 1.0 if up else 0.0)
                    outages.add_metric([category, device_id], float(max(slot.outages,
                                                                        health.outages if health else 0)))
                    if category == "robot":
                        connected.add_metric([device_id], 1.0 if up else 0.0)
                    if category != "camera":
                        continue
                    for family, count in ((frames, health.frames_received if health else None),
                                          (lost, health.frames_lost if health else None),
                                          (incomplete, health.frames_incomplete if health else None)):
                        if count is not None:
                            family.add_metric([device_id], float(count))
                    fps = _number(self._settings(device_id, slot).get("frame_rate_hz")) if slot.is_open else None
                    if fps is not None:
                        rate.add_metric([device_id], fps)
        yield from (available, outages, connected, frames, lost, incomplete, rate)

    def _settings(self, device_id: str, slot: DeviceSlot[Any]) -> dict[str, Any]:
        """The camera's ``settings()``, or {} when it fails or does not answer in time.

        Asked in a daemon thread, so a camera that hangs delays a scrape by at most
        ``SETTINGS_TIMEOUT_S`` and never blocks the process from exiting.
        """
        with self._lock:
            pending = self._pending.get(device_id)
            if pending is not None and pending.is_alive():
                return {}  # the previous scrape's call is still stuck in the device: do not pile up
            box: dict[str, Any] = {}

            def ask() -> None:
                try:
                    box["settings"] = slot.device.settings()
                except Exception:  # noqa: BLE001 - a scrape reports what it can
                    log.debug("camera %s settings() failed", device_id, exc_info=True)

            thread = threading.Thread(target=ask, name=f"metrics-{device_id}", daemon=True)
            self._pending[device_id] = thread
            thread.start()
        thread.join(SETTINGS_TIMEOUT_S)
        if thread.is_alive():
            log.debug("camera %s settings() did not answer within %.1f s", device_id, SETTINGS_TIMEOUT_S)
            return {}
        result = box.get("settings")
        return result if isinstance(result, dict) else {}


def _health(slot: DeviceSlot[Any]) -> DeviceHealth | None:
    """The adapter's ``health()``, None for adapters that do not report it."""
    if not isinstance(slot.device, Monitored):
        return None
    try:
        return slot.device.health()
    except Exception:  # noqa: BLE001 - a scrape reports what it can
        log.debug("%s health() failed", slot.device_id, exc_info=True)
        return DeviceHealth(available=False, reason="health() failed")


def _number(v: Any) -> float | None:
    if isinstance(v, bool) or not isinstance(v, int | float):
        return None
    return float(v)


# -- the function API (each service's metrics are its own: no module-level registry) ------------------


class _HasMetrics(Protocol):
    metrics: CellMetrics


def attach(metrics: CellMetrics, services: Any) -> None:
    """Make ``metrics`` the metrics of ``services`` (its picks, its jobs, its cell's devices)."""
    services.metrics = metrics
    services.jobs.metrics = metrics
    metrics.attach(services.cell)


def detach(metrics: CellMetrics) -> None:
    """Record nothing more in ``metrics`` (its service closed); its registry keeps the counts."""
    metrics.detach()


def observe_pick(latency_s: float, scores: Iterable[float], source: _HasMetrics) -> None:
    """Record one pick in ``source``'s metrics (a ``Services``); never raises."""
    source.metrics.observe_pick(latency_s, list(scores))

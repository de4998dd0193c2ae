"""The FastAPI application factory. Devices are opened in the lifespan, never at import."""

from __future__ import annotations

import logging
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI
from starlette.concurrency import run_in_threadpool

from cellctl import __version__, metrics
from cellctl.api.connections import ACCEPT_BACKLOG, guarded_protocol, raise_open_files_limit
from cellctl.api.errors import install_error_handlers
from cellctl.api.middleware import RequestMiddleware
from cellctl.api.pools import Pools
from cellctl.api.routes import auth, calibrations, cameras, health, jobs, map, pick, robots, targets, ui
from cellctl.api.routes import drift as drift_route
from cellctl.api.routes import metrics as metrics_route
from cellctl.api.routes import plc as plc_route
from cellctl.api.routes import production as production_route
from cellctl.api.routes import recipes as recipes_route
from cellctl.api.routes import sim as sim_route
from cellctl.auth import TokenTable
from cellctl.cell import Cell
from cellctl.config import CellConfig, Role
from cellctl.jobs import JobManager
from cellctl.latches import LatchKeeper
from cellctl.production.interrupted import end_interrupted_runs
from cellctl.services import Services
from cellctl.warmup import service_startup

log = logging.getLogger(__name__)

__all__ = ["ACCEPT_BACKLOG", "create_app", "guarded_protocol", "raise_open_files_limit"]
"""``cellctl serve`` (the one door from the CLI) builds the app and its HTTP protocol from here."""


def create_app(config: CellConfig, session_tokens: list[tuple[str, Role, str]] | None = None) -> FastAPI:
    """Build the service for a cell. ``session_tokens`` are (name, role, sha256) valid for this run."""

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        from cellctl.store import open_store

        t0 = time.monotonic()  # the start-up's "ready in" counts from here
        cell = Cell(config)
        store = await run_in_threadpool(open_store, config)
        # Robots latched before a crash or restart are latched again before anything is served.
        owners = {rid: slot.device.motion for rid, slot in cell.robots.items()}
        latches = LatchKeeper(store, owners)
        await run_in_threadpool(latches.restore)
        # A production run the service did not end (killed) ends `interrupted` now, its robot latched.
        await run_in_threadpool(end_interrupted_runs, store, owners)
        latches.start()
        services = Services(config, cell, store, JobManager(), latches=latches, metrics=app.state.metrics)
        # The production manager now: REST and the PLC show the last stored run at once.
        await run_in_threadpool(lambda: services.production)
        app.state.cell = cell
        app.state.services = services
        await run_in_threadpool(cell.open_all)
        # The compiled loops (renderer, matcher, solver) load in the background; /health says
        # `starting` until they have, and a camera image waits for its camera's (cellctl.warmup).
        app.state.startup = service_startup(cell, since_s=t0)
        app.state.startup.start()
        drift = await run_in_threadpool(lambda: services.drift)
        if drift is not None:
            drift.start()  # the idle checks (docs/drift.md); joined by services.close
        log.info("cell %s open: cameras %s, robots %s; store %s; warming up", config.cell_id, sorted(cell.cameras),
                 sorted(cell.robots), store.describe())
        from cellctl.plc import start_plc_servers

        try:
            plc = await run_in_threadpool(start_plc_servers, services)
        except BaseException as exc:
            log.error("the PLC servers cannot start: %s", exc)
            await run_in_threadpool(services.close)
            await run_in_threadpool(app.state.startup.stop)
            raise
        try:
            yield
        finally:
            # A production run in progress ends stopped, its robot halted and its records written,
            # before the PLC and the devices go.
            await run_in_threadpool(services.stop_production)
            await run_in_threadpool(plc.stop)
            await run_in_threadpool(services.close)
            await run_in_threadpool(app.state.startup.stop)

    app = FastAPI(
        title="cellctl",
        version=__version__,
        description="Robot work-cell controller: cameras, robots, calibration, pick guidance. "
                    "Every route except /health, /docs and /openapi.json needs 'Authorization: Bearer TOKEN'.",
        lifespan=lifespan,
        docs_url=None, redoc_url=None,  # served from local assets by routes/ui.py (no CDN)
    )
    app.state.config = config
    app.state.tokens = TokenTable.from_config(config, session_tokens)
    app.state.metrics = metrics.CellMetrics()
    app.state.pools = Pools()  # worker-thread pools the safety routes and large bodies have to themselves
    app.add_middleware(RequestMiddleware, metrics=app.state.metrics)
    install_error_handlers(app)
    for module in (health, auth, cameras, robots, targets, calibrations, jobs, map, pick, ui):
        app.include_router(module.router)
    app.include_router(metrics_route.router)
    app.include_router(sim_route.router)
    app.include_router(production_route.router)
    app.include_router(recipes_route.router)
    app.include_router(plc_route.router)
    app.include_router(drift_route.router)
    return app

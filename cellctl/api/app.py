"""The FastAPI application factory. Devices are opened in the lifespan, never at import."""

from __future__ import annotations

import logging
import threading
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI
from starlette.concurrency import run_in_threadpool

from cellctl import __version__, metrics
from cellctl.api.errors import install_error_handlers
from cellctl.api.middleware import RequestMiddleware
from cellctl.api.pools import Pools
from cellctl.api.routes import auth, calibrations, cameras, health, jobs, map, pick, robots, targets, ui
from cellctl.api.routes import metrics as metrics_route
from cellctl.api.routes import production as production_route
from cellctl.api.routes import sim as sim_route
from cellctl.auth import TokenTable
from cellctl.cell import Cell
from cellctl.config import CellConfig, Role
from cellctl.jobs import JobManager
from cellctl.latches import LatchKeeper
from cellctl.services import Services

log = logging.getLogger(__name__)


def _warm_up_matcher() -> None:
    from vision.shape import warm_up

    try:
        warm_up()
    except Exception:  # noqa: BLE001 - a failed warm-up only costs the first search its load time
        log.warning("loading the matcher's compiled loops failed; the first search will load them", exc_info=True)


def create_app(config: CellConfig, session_tokens: list[tuple[str, Role, str]] | None = None) -> FastAPI:
    """Build the service for a cell. ``session_tokens`` are (name, role, sha256) valid for this run."""

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        from cellctl.store import open_store

        cell = Cell(config)
        store = await run_in_threadpool(open_store, config)
        # Robots latched before a crash or restart are latched again before anything is served.
        latches = LatchKeeper(store, {rid: slot.device.motion for rid, slot in cell.robots.items()})
        await run_in_threadpool(latches.restore)
        latches.start()
        services = Services(config, cell, store, JobManager(), latches=latches)
        app.state.cell = cell
        app.state.services = services
        metrics.attach(app.state.metrics, services)
        await run_in_threadpool(cell.open_all)
        # The matcher's compiled loops load in the background, so the first pick costs what the next ones do.
        threading.Thread(target=_warm_up_matcher, name="matcher-warm-up", daemon=True).start()
        log.info("cell %s ready: cameras %s, robots %s; store %s", config.cell_id, sorted(cell.cameras),
                 sorted(cell.robots), store.describe())
        from cellctl.plc import start_plc_servers

        try:
            plc = await run_in_threadpool(start_plc_servers, services)
        except BaseException as exc:
            log.error("the PLC servers cannot start: %s", exc)
            await run_in_threadpool(services.close)
            metrics.detach(app.state.metrics)
            raise
        try:
            yield
        finally:
            await run_in_threadpool(plc.stop)
            await run_in_threadpool(services.close)
            metrics.detach(app.state.metrics)

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
    return app

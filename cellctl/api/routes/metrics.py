"""``GET /metrics``: the cell's Prometheus metrics (text exposition format); needs a viewer token."""

from __future__ import annotations

from fastapi import APIRouter, Request, Response
from starlette.concurrency import run_in_threadpool

from cellctl.api.deps import Viewer
from cellctl.metrics import CONTENT_TYPE, CellMetrics

router = APIRouter(tags=["metrics"])


@router.get("/metrics", response_class=Response,
            responses={200: {"content": {"text/plain": {}}, "description": "Prometheus text format"}})
async def metrics(request: Request, _: Viewer) -> Response:
    cell_metrics: CellMetrics = request.app.state.metrics
    # A scrape reads the device slots (and may wait briefly for a camera): keep it off the event loop.
    body = await run_in_threadpool(cell_metrics.render)
    return Response(content=body, media_type=CONTENT_TYPE)

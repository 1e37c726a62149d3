"""What ops and operators read: liveness, readiness, metrics (the scraper's token), the console page.

GET /health and GET /ready are answered before routing by `service.probes.ProbeAnswers` (installed by
create_app); their routes here describe them in the OpenAPI schema and answer the same way for an app
mounted without that middleware."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import HTMLResponse, JSONResponse, PlainTextResponse, Response

from service import console
from service.deps import MetricsReader, State
from service.metrics import CONTENT_TYPE as METRICS_CONTENT_TYPE
from service.schemas import HealthOut, ReadyOut

router = APIRouter(tags=["service"])
ERROR_SCHEMA = {"$ref": "#/components/schemas/ErrorOut"}
#: the console page's headers
CONSOLE_HEADERS = {
    "Referrer-Policy": "no-referrer",
    "X-Frame-Options": "DENY",
    "Content-Security-Policy": "frame-ancestors 'none'",
}


@router.get("/health", response_model=HealthOut, summary="Liveness")
async def health(state: State) -> HealthOut:
    return state.health_report()


@router.get(
    "/ready",
    response_model=ReadyOut,
    responses={503: {"model": ReadyOut, "description": "not ready; detail says why"}},
    summary="Readiness: model and library loaded, checked and warmed up",
)
async def ready(state: State) -> JSONResponse:
    body, status = state.ready_report()
    return JSONResponse(body.model_dump(), status_code=status)


@router.get(
    "/metrics",
    response_class=PlainTextResponse,
    responses={
        200: {"content": {"text/plain": {"example": "hapticlink_windows_total 1234\n"}}},
        # its refusals are JSON, not the text/plain FastAPI would document them as after the route's response class
        **{
            code: {"description": why, "content": {"application/json": {"schema": ERROR_SCHEMA}}}
            for code, why in ((401, "no metrics token, or another"), (403, "no metrics token is configured"))
        },
    },
    dependencies=[MetricsReader],
    summary="Prometheus metrics (text exposition; the metrics token, HAPTICLINK_METRICS_TOKEN)",
)
async def metrics(state: State) -> Response:
    return Response(state.metrics.render(), media_type=METRICS_CONTENT_TYPE)


@router.get(
    "/console",
    response_class=HTMLResponse,
    summary="The operator console (open with ?session=…&token=<operator token>)",
)
async def console_page() -> HTMLResponse:
    # The URL carries the operator token: never send it on as a Referer, and no other site may frame the page.
    return HTMLResponse(console.page(), headers=CONSOLE_HEADERS)


@router.get(
    "/console/render-worklet.js",
    response_class=PlainTextResponse,
    responses={200: {"content": {"text/javascript": {}}}},
    summary="The console's texture renderer (an AudioWorklet module; no credential: it holds no data)",
)
async def console_render_worklet() -> Response:
    return Response(console.render_worklet(), media_type="text/javascript", headers={"Cache-Control": "no-cache"})


@router.get(
    "/console/model-codec.js",
    response_class=PlainTextResponse,
    responses={200: {"content": {"text/javascript": {}}}},
    summary="The console's decoder of compact models and deltas (no credential: it holds no data)",
)
async def console_model_codec() -> Response:
    return Response(console.model_codec(), media_type="text/javascript", headers={"Cache-Control": "no-cache"})

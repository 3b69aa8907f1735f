"""The monitor's web application (Starlette): the page, the status JSON, thumbnails, server-sent events.

Read-only: every route is a GET, and nothing a request carries reaches the source but a camera or
take name that is checked against the source's own lists first. One background task samples the
source a few times a second (SAMPLE_PERIOD_S) and derives the status; requests and the event
streams read that status, so any number of pages cost the recorder one snapshot per sample.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import secrets
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

from starlette.applications import Starlette
from starlette.concurrency import run_in_threadpool
from starlette.requests import Request
from starlette.responses import HTMLResponse, Response, StreamingResponse
from starlette.routing import Route
from starlette.types import ASGIApp, Receive, Scope, Send

from manus_core.errors import ManusError

from .derive import Deriver, derive
from .recorded import RecordedSource, RecordedTake
from .source import MonitorSource
from .thumbs import BUDGET, Thumbnails

SAMPLE_PERIOD_S = 0.25    # the source is sampled, and the page sent its status, this often
PAGE = Path(__file__).with_name("page.html")
NO_STORE = {"Cache-Control": "no-store"}


def _plain(value: Any) -> Any:
    """numpy scalars (a source may count in them) as JSON numbers."""
    if hasattr(value, "item"):
        return value.item()
    raise TypeError(f"{type(value).__name__} is not JSON serializable")


def json_response(content: Any, status_code: int = 200) -> Response:
    return Response(json.dumps(content, default=_plain), status_code=status_code,
                    media_type="application/json", headers=NO_STORE)


class TokenGate:
    """Every HTTP request must carry the token: ?token=, `Authorization: Bearer`, or X-Monitor-Token."""

    def __init__(self, app: ASGIApp, token: str) -> None:
        self.app, self.token = app, token

    def _given(self, scope: Scope) -> str:
        request = Request(scope)
        bearer = request.headers.get("authorization", "")
        return (request.query_params.get("token") or request.headers.get("x-monitor-token")
                or (bearer[7:] if bearer.lower().startswith("bearer ") else ""))

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http" and not secrets.compare_digest(self._given(scope).encode(), self.token.encode()):
            await Response("401: this monitor needs its token (?token=...)\n", status_code=401,
                           media_type="text/plain")(scope, receive, send)
            return
        await self.app(scope, receive, send)


class Monitor:
    """The state the routes share: the source, the latest derived status, the thumbnail cache."""

    def __init__(self, source: MonitorSource) -> None:
        self.source = source
        self.deriver = Deriver()
        self.status: dict | None = None
        self.changed = asyncio.Event()
        # a recording needs its CPU: only live thumbnails are held to the budget (thumbs.BUDGET)
        self.thumbs = Thumbnails(budget=None if isinstance(source, RecordedSource) else BUDGET)
        self.closing = False   # set by MonitorServer.stop(): the event streams end, so that the server can

    async def sample(self) -> dict:
        """Sample the source once and derive; a source that fails is reported, never raised."""
        try:
            snap = await run_in_threadpool(self.source.snapshot)
            status = self.deriver.add(snap)
            status["source_error"] = None
        except Exception as exc:   # the monitor outlives a failing source (and never stops it)
            status = {**(self.status or {"cameras": [], "alerts": []}),
                      "source_error": f"{type(exc).__name__}: {exc}"}
        self.status = status
        changed, self.changed = self.changed, asyncio.Event()
        changed.set()
        return status

    async def sample_forever(self) -> None:
        while True:
            await self.sample()
            await asyncio.sleep(SAMPLE_PERIOD_S)

    def recorded_take(self, request: Request) -> RecordedTake | None:
        """The take a request about a recorded source names (?take=; KeyError if unknown), None when live."""
        if not isinstance(self.source, RecordedSource):
            return None
        return self.source.take(request.query_params.get("take"))

    async def status_for(self, request: Request) -> dict:
        take = self.recorded_take(request)
        if take is None:
            return self.status if self.status is not None else await self.sample()
        snap = await run_in_threadpool(take.snapshot)
        status = derive(snap, 0.0, 0.0, snap)
        status["review"] = {"takes": self.source.summary(), "take": take.name}
        return status


def _unknown(what: str, name: str, known: list[str]) -> Response:
    return json_response({"error": f"no {what} {name!r}", f"{what}s": known}, 404)


def build_app(source: MonitorSource, token: str | None = None) -> tuple[ASGIApp, Monitor]:
    """The ASGI application over `source` (behind the token gate when a token is given), and its state."""
    monitor = Monitor(source)
    page = PAGE.read_bytes()

    async def index(request: Request) -> Response:
        return HTMLResponse(page, headers=NO_STORE)

    def recorded(handler: Callable) -> Callable:
        """Run `handler(request, take)`; an unknown ?take= is a 404 with the known takes."""
        async def route(request: Request) -> Response:
            try:
                take = monitor.recorded_take(request)
            except KeyError:
                return _unknown("take", request.query_params["take"], list(source.takes))
            try:
                return await handler(request, take)
            except ManusError as exc:   # a recorded file that cannot be read (TakeError names it)
                return json_response({"error": str(exc)}, 500)
        return route

    async def status(request: Request, take: RecordedTake | None) -> Response:
        return json_response(await monitor.status_for(request))

    async def thumbnail(request: Request, take: RecordedTake | None) -> Response:
        cam = request.path_params["cam"]
        shown = take or source
        if cam not in shown.camera_ids():
            return _unknown("camera", cam, shown.camera_ids())
        if take is None:
            read, key = (lambda: source.latest_jpeg(cam)), cam
        else:
            try:
                k = int(request.query_params.get("frame", "0"))
            except ValueError:
                return json_response({"error": "frame: expected a frame index (an integer)"}, 400)
            read, key = (lambda: take.frame_jpeg(cam, k)), (take.name, cam)

        def make() -> bytes | None:
            jpeg = read()
            return None if jpeg is None else monitor.thumbs.get(key, jpeg)
        try:
            thumb = await run_in_threadpool(make)
        except KeyError:   # the camera went away from a live source between the check and the read
            return _unknown("camera", cam, source.camera_ids())
        if thumb is None:
            return Response(status_code=204, headers=NO_STORE)
        return Response(thumb, media_type="image/jpeg", headers=NO_STORE)

    async def timeline(request: Request, take: RecordedTake | None) -> Response:
        png = None if take is None else await run_in_threadpool(take.timeline_png)
        if png is None:
            return json_response({"error": "no sync timeline (run sync-report on the take)"}, 404)
        return Response(png, media_type="image/png")

    async def events(request: Request, take: RecordedTake | None) -> Response:
        async def stream() -> AsyncIterator[str]:
            while not monitor.closing:
                yield f"data: {json.dumps(await monitor.status_for(request), default=_plain)}\n\n"
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(monitor.changed.wait(), SAMPLE_PERIOD_S * 4)
        return StreamingResponse(stream(), media_type="text/event-stream",
                                 headers={**NO_STORE, "X-Accel-Buffering": "no"})

    @contextlib.asynccontextmanager
    async def lifespan(app: Starlette) -> AsyncIterator[None]:
        sampler = asyncio.create_task(monitor.sample_forever())
        try:
            yield
        finally:
            sampler.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await sampler

    app: ASGIApp = Starlette(routes=[
        Route("/", index),
        Route("/api/status", recorded(status)),
        Route("/api/events", recorded(events)),
        Route("/api/cameras/{cam}/latest.jpg", recorded(thumbnail)),
        Route("/api/timeline.png", recorded(timeline)),
    ], lifespan=lifespan)
    return (TokenGate(app, token) if token else app), monitor

"""The workbench's HTTP layer: the JSON API (one table, :data:`ENDPOINTS`, gives the routes and the OpenAPI
document at ``/api/openapi.json``), server-sent events, the page, token access, and a uvicorn server thread.

Every error is JSON ``{"error": reason}`` with a 4xx status (5xx only for a bug, without a traceback); the server
keeps running.
"""

from __future__ import annotations

import asyncio
import hmac
import ipaddress
import json
import logging
import math
import socket
import threading
from collections.abc import Callable, MutableMapping
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import uvicorn
from starlette.applications import Starlette
from starlette.exceptions import HTTPException
from starlette.requests import Request
from starlette.responses import FileResponse, JSONResponse, Response, StreamingResponse
from starlette.routing import Mount, Route
from starlette.staticfiles import StaticFiles
from starlette.types import ASGIApp, Receive, Scope, Send

from nodes.workbench.service import ApiError, Workbench, at_ns_of

log = logging.getLogger("constructaide.workbench")
STATIC = Path(str(resources.files("nodes.workbench") / "static"))
TOKEN_COOKIE = "workbench_token"


def is_loopback(host: str) -> bool:
    """Whether ``host`` only accepts connections from this machine."""
    if host in ("localhost", ""):
        return host == "localhost"
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


# ---------------------------------------------------------------------------------------------------- handlers


MAX_BODY_BYTES = 1 << 20
"""Largest request body (anchor clicks, selections, annotations are a few kB): 413 beyond."""
INT64 = 1 << 63


def int64(raw: str) -> int:
    """An integer that fits int64 (times in ns, indices); ValueError otherwise."""
    v = int(raw)
    if not -INT64 <= v < INT64:
        raise ValueError(f"{raw[:40]} is outside the int64 range")
    return v


def finite_float(raw: str) -> float:
    """A finite float (pixels, radii); ValueError for NaN, infinities and overflow."""
    v = float(raw)
    if not math.isfinite(v):
        raise ValueError(f"{raw[:40]} is not finite")
    return v


def _q(req: Request, name: str, conv: Callable[[str], Any] = str, default: Any = ...) -> Any:
    raw = req.query_params.get(name)
    if raw is None:
        if default is ...:
            raise ApiError(400, f"query parameter {name!r} is required")
        return default
    try:
        return conv(raw)
    except ValueError:
        what = {"int64": "integer (int64)", "finite_float": "finite number"}.get(conv.__name__, conv.__name__)
        raise ApiError(400, f"query parameter {name}={raw[:60]!r} is not a valid {what}") from None


async def _body(req: Request) -> bytes:
    """The request body, at most :data:`MAX_BODY_BYTES` (413 beyond, before reading it all)."""
    declared = req.headers.get("content-length", "")
    if declared.isdigit() and int(declared) > MAX_BODY_BYTES:
        raise ApiError(413, f"request body of {declared} bytes is larger than the limit of {MAX_BODY_BYTES}")
    chunks, n = [], 0
    async for chunk in req.stream():
        n += len(chunk)
        if n > MAX_BODY_BYTES:
            raise ApiError(413, f"request body is larger than the limit of {MAX_BODY_BYTES} bytes")
        chunks.append(chunk)
    return b"".join(chunks)


def _no_constant(name: str) -> Any:
    raise ValueError(f"{name} is not a JSON number")


def strict_json(body: bytes) -> Any:
    """JSON of a request body: no NaN / Infinity, floats finite, integers within int64 (else ApiError 400)."""
    try:
        return json.loads(body or b"{}", parse_constant=_no_constant, parse_float=finite_float, parse_int=int64)
    except json.JSONDecodeError as e:
        raise ApiError(400, f"body is not valid JSON: {e}") from None
    except (ValueError, UnicodeDecodeError) as e:
        raise ApiError(400, f"body is not acceptable JSON: {str(e)[:200]}") from None
    except RecursionError:
        raise ApiError(400, "body JSON is nested too deeply") from None


async def _json(req: Request) -> Any:
    return strict_json(await _body(req))


def _obj(x: Any) -> dict[str, Any]:
    if not isinstance(x, dict):
        raise ApiError(400, "body must be a JSON object")
    return x


def _wb(req: Request) -> Workbench:
    return req.app.state.workbench


def _png(data: bytes) -> Response:
    return Response(data, media_type="image/png", headers={"Cache-Control": "no-cache"})


def _ids(req: Request) -> list[str]:
    return [x for x in _q(req, "element_ids", str, "").split(",") if x]


async def site(req: Request) -> JSONResponse:
    wb = _wb(req)
    st = wb.state
    return JSONResponse(
        {
            "site": wb.site,
            "live": wb.live,
            "model_revision": st.model.revision if st.model is not None else None,
            "photos": len(st.photos),
            "needs_anchor": len(st.needs_anchor),
            "annotations": len(st.current_annotations()),
            "event_seq": wb.events.seq,
        }
    )


def photos(req: Request) -> JSONResponse:
    return JSONResponse(_wb(req).state.photo_list())


def photo(req: Request) -> JSONResponse:
    return JSONResponse(_wb(req).photo_detail(req.path_params["photo_id"]))


def image(req: Request) -> Response:
    p = _wb(req).photo(req.path_params["photo_id"])
    return Response(p.data, media_type=p.media_type, headers={"Cache-Control": "max-age=86400"})


def thumb(req: Request) -> Response:
    data = _wb(req).thumbnail(req.path_params["photo_id"])
    return Response(data, media_type="image/jpeg", headers={"Cache-Control": "max-age=86400"})


def overlay(req: Request) -> Response:
    return _png(_wb(req).overlay_png(req.path_params["photo_id"], req.path_params["mode"]))


def mask(req: Request) -> Response:
    return _png(_wb(req).mask_png(req.path_params["photo_id"], req.path_params["kind"]))


def anchor_queue(req: Request) -> JSONResponse:
    return JSONResponse(_wb(req).anchor_queue())


def model(req: Request) -> JSONResponse:
    return JSONResponse(_wb(req).model_info())


def model_glb(req: Request) -> Response:
    return Response(_wb(req).model().geometry_glb, media_type="model/gltf-binary")


def model_mesh(req: Request) -> Response:
    return Response(_wb(req).geometry().mesh_bytes(), media_type="application/octet-stream")


def visible(req: Request) -> JSONResponse:
    return JSONResponse({"at_ns": (t := _q(req, "at_ns", int64)), "indices": _wb(req).visible_indices(t)})


def pick(req: Request) -> JSONResponse:
    wb = _wb(req)
    u, v = _q(req, "u", finite_float), _q(req, "v", finite_float)
    out = wb.pick_photo(_q(req, "photo_id"), u, v, _q(req, "snap_px", finite_float, 0.0))
    return JSONResponse(out)


async def pick_view(req: Request) -> JSONResponse:
    body = _obj(await _json(req))
    return JSONResponse(await asyncio.to_thread(_wb(req).pick_view, body))


ANCHOR_BODY = '{"points": [{"pixel": [u, v], "world": [x, y, z]}, ...]}'


async def _anchor_body(req: Request) -> bytes:
    """The body of solve / anchors, checked as strict JSON (NaN, infinities, huge numbers, deep nesting: 400)
    before the typed decode."""
    body = await _body(req)
    try:
        strict_json(body)
    except ApiError as e:
        raise ApiError(400, f"body must be {ANCHOR_BODY}: {e.reason}") from None
    return body


async def solve(req: Request) -> JSONResponse:
    out = await asyncio.to_thread(_wb(req).solve, req.path_params["photo_id"], await _anchor_body(req))
    out.pop("_req", None)
    return JSONResponse(out)


async def anchors(req: Request) -> JSONResponse:
    body = await _anchor_body(req)
    return JSONResponse(await asyncio.to_thread(_wb(req).submit_anchors, req.path_params["photo_id"], body))


async def select(req: Request) -> JSONResponse:
    body = _obj(await _json(req))
    return JSONResponse(await asyncio.to_thread(_wb(req).select, req.path_params["photo_id"], body))


def outline(req: Request) -> JSONResponse:
    return JSONResponse({"polygons": _wb(req).outline(req.path_params["photo_id"], _ids(req))})


def progress(req: Request) -> JSONResponse:
    return JSONResponse(_wb(req).progress(req.path_params["photo_id"]))


def review_queue(req: Request) -> JSONResponse:
    return JSONResponse(_wb(req).review_queue(_q(req, "limit", int64, 50)))


async def review(req: Request) -> JSONResponse:
    body = _obj(await _json(req))
    out = await asyncio.to_thread(_wb(req).review_detection, req.path_params["photo_id"], body)
    return JSONResponse(out, status_code=201)


def element(req: Request) -> JSONResponse:
    g = _wb(req).geometry()
    try:
        return JSONResponse(g.element_info(req.path_params["global_id"], _q(req, "at_ns", int64, None)))
    except KeyError:
        raise ApiError(404, f"unknown element {req.path_params['global_id']!r}") from None


def list_annotations(req: Request) -> JSONResponse:
    pid = _q(req, "photo_id", str, None)
    wb = _wb(req)
    if pid is not None:
        wb.photo(pid)
    return JSONResponse(wb.annotations(pid))


async def create_annotation(req: Request) -> JSONResponse:
    body = _obj(await _json(req))
    return JSONResponse(await asyncio.to_thread(_wb(req).create_annotation, body), status_code=201)


async def update_annotation(req: Request) -> JSONResponse:
    body = _obj(await _json(req))
    return JSONResponse(await asyncio.to_thread(_wb(req).create_annotation, body, req.path_params["annotation_id"]))


def delete_annotation(req: Request) -> JSONResponse:
    return JSONResponse(_wb(req).delete_annotation(req.path_params["annotation_id"]))


def history(req: Request) -> JSONResponse:
    return JSONResponse(_wb(req).history(req.path_params["annotation_id"]))


async def peek(req: Request) -> Response:
    body = _obj(await _json(req))
    if "at_ns" not in body:
        raise ApiError(400, 'peek needs {"at_ns": int, "polygon": [[u, v], ...] (optional)}')
    at, poly = at_ns_of(body["at_ns"]), body.get("polygon")
    png, meta = await asyncio.to_thread(_wb(req).peek, req.path_params["photo_id"], at, poly)
    return Response(png, media_type="image/png", headers={"X-Peek": json.dumps(meta)})


def preview(req: Request) -> Response:
    return _png(_wb(req).preview(req.path_params["photo_id"], _ids(req)))


async def events(req: Request) -> StreamingResponse:
    wb = _wb(req)
    loop = asyncio.get_running_loop()
    queue: asyncio.Queue[dict[str, Any]] = asyncio.Queue()
    stop: threading.Event = req.app.state.stopping

    def deliver(ev: dict[str, Any]) -> None:
        try:
            loop.call_soon_threadsafe(queue.put_nowait, ev)
        except RuntimeError:  # the loop is gone
            pass

    unsubscribe = wb.events.subscribe(deliver)

    async def stream():  # noqa: ANN202 - async generator
        try:
            yield f"retry: 2000\ndata: {json.dumps({'kind': 'hello', 'seq': wb.events.seq})}\n\n"
            while not stop.is_set():
                try:
                    ev = await asyncio.wait_for(queue.get(), timeout=1.0)
                except TimeoutError:
                    yield ": keep-alive\n\n"
                    continue
                yield f"data: {json.dumps(ev)}\n\n"
        finally:
            unsubscribe()

    return StreamingResponse(stream(), media_type="text/event-stream", headers={"Cache-Control": "no-cache"})


def openapi(req: Request) -> JSONResponse:
    return JSONResponse(openapi_document())


def index(req: Request) -> Response:
    resp = FileResponse(STATIC / "index.html", headers={"Cache-Control": "no-cache"})
    token = req.query_params.get("token")
    if token:
        resp.set_cookie(TOKEN_COOKIE, token, httponly=True, samesite="strict")
    return resp


# ---------------------------------------------------------------------------------------------------- table


@dataclass(frozen=True)
class Endpoint:
    method: str
    path: str
    handler: Callable[..., Any]
    summary: str
    params: tuple[str, ...] = ()
    body: str = ""
    returns: str = "application/json"


ENDPOINTS: tuple[Endpoint, ...] = (
    Endpoint("GET", "/api/site", site, "Site id, live mode, model revision and counts"),
    Endpoint(
        "GET",
        "/api/photos",
        photos,
        'Every photo: [{"photo_id", "filename", "camera_id", "capture_time" (ns UTC), "status" (anchor, auto, '
        "failed, needs_anchor, pending), registration quality, overlay modes, masks}] in capture order",
    ),
    Endpoint("GET", "/api/photos/{photo_id}", photo, "One photo with its registration and viewpoint neighbours"),
    Endpoint("GET", "/api/photos/{photo_id}/image", image, "The photo (JPEG/PNG as pushed)", returns="image/jpeg"),
    Endpoint("GET", "/api/photos/{photo_id}/thumb", thumb, "240 px wide JPEG thumbnail", returns="image/jpeg"),
    Endpoint(
        "GET", "/api/photos/{photo_id}/overlay/{mode}", overlay, "The render node's overlay PNG", returns="image/png"
    ),
    Endpoint(
        "GET", "/api/photos/{photo_id}/mask/{kind}", mask, "An occlusion mask PNG (255 = occluded)", returns="image/png"
    ),
    Endpoint("GET", "/api/anchor-queue", anchor_queue, "Open NeedsAnchor requests (photos to click)"),
    Endpoint("GET", "/api/model", model, "Elements with IFC attributes and tasks, bounding box, time range"),
    Endpoint(
        "GET",
        "/api/model.glb",
        model_glb,
        "The model geometry (GLB, z up, one node per element)",
        returns="model/gltf-binary",
    ),
    Endpoint(
        "GET",
        "/api/model/mesh.bin",
        model_mesh,
        "Triangles and feature edges for WebGL (uint32 T, K; float32 T*9; uint32 T owners; float32 K*6; uint32 K)",
        returns="application/octet-stream",
    ),
    Endpoint("GET", "/api/model/visible", visible, "Indices of elements standing at at_ns", ("at_ns",)),
    Endpoint(
        "GET",
        "/api/pick",
        pick,
        'Element under pixel (u, v) of a registered photo: {"global_id", "ifc_class", "point_in_world_m": [x, y, z]} '
        'or {"global_id": null}',
        ("photo_id", "u", "v", "snap_px"),
    ),
    Endpoint(
        "POST",
        "/api/pick",
        pick_view,
        "Element and 3D point under a pixel of a model view (ray cast, snapped to a corner or edge within snap_px)",
        body='{"world_from_camera": [16], "intrinsics": {"width_px", "height_px", "f_px", "cx_px", "cy_px"}, "u", '
        '"v", "at_ns"?, "snap_px"?}',
    ),
    Endpoint(
        "POST",
        "/api/photos/{photo_id}/solve",
        solve,
        "Live pose solve from >= 4 clicks (nothing published): residuals, mis-click flags, pose",
        body='{"points": [{"pixel": [u, v], "world": [x, y, z]}, ...]}',
    ),
    Endpoint(
        "POST",
        "/api/photos/{photo_id}/anchors",
        anchors,
        'Submit anchor clicks: {"residuals_px": [...], "world_from_camera": [16], ...}; published as AnchorClicks '
        "in live mode",
        body='{"points": [{"pixel": [u, v], "world": [x, y, z]}, ...], "author"?}',
    ),
    Endpoint(
        "POST",
        "/api/photos/{photo_id}/select",
        select,
        "Selection: click (u, v), grow (element_ids, by: ifc_class|type_name|material|storey|task), region "
        "(polygon | brush + radius_px), occlusion (u, v, kind)",
        body='{"mode": "click"|"grow"|"region"|"occlusion", ...}',
    ),
    Endpoint("GET", "/api/photos/{photo_id}/outline", outline, "Outlines of elements' visible parts", ("element_ids",)),
    Endpoint(
        "GET",
        "/api/photos/{photo_id}/progress",
        progress,
        "What the progress node read in the photo: per element its reading there, its fused progress (P, deviation, "
        "dates) and the latest person's review",
    ),
    Endpoint(
        "GET",
        "/api/progress/review-queue",
        review_queue,
        "Readings that disagree with the plan (built before the planned start, not built after the planned finish), "
        "one per element not reviewed yet, the farthest off schedule first",
        ("limit",),
    ),
    Endpoint(
        "POST",
        "/api/photos/{photo_id}/progress/review",
        review,
        "Confirm or correct the reading of an element: a status annotation (built / not built) on it, published in "
        "live mode; the progress node takes it as evidence",
        body='{"global_id", "verdict": "confirm"|"built"|"not_built", "author"?, "text"?}',
    ),
    Endpoint("GET", "/api/elements/{global_id}", element, "IFC attributes and state of one element", ("at_ns",)),
    Endpoint(
        "GET",
        "/api/annotations",
        list_annotations,
        "Current annotations; with photo_id only those showing there, each with its transferred polygons",
        ("photo_id",),
    ),
    Endpoint(
        "POST",
        "/api/annotations",
        create_annotation,
        "Create an annotation (published as an Annotation message in live mode)",
        body='{"photo_id", "element_ids"? , "polygon_px"?, "status"?, "rgba"?, "text"?, "kind"?, "author"?}',
    ),
    Endpoint(
        "PUT", "/api/annotations/{annotation_id}", update_annotation, "Edit: a new revision", body="fields to change"
    ),
    Endpoint("DELETE", "/api/annotations/{annotation_id}", delete_annotation, "Delete: a last revision, deleted"),
    Endpoint("GET", "/api/annotations/{annotation_id}/history", history, "Every revision of an annotation"),
    Endpoint(
        "POST",
        "/api/photos/{photo_id}/peek",
        peek,
        "Peek at at_ns inside a polygon: an earlier photo of the viewpoint group warped by its homography, or the "
        "model's future state; RGBA PNG, X-Peek header {direction, source_photo_id}",
        body='{"at_ns": int, "polygon": [[u, v], ...]?}',
        returns="image/png",
    ),
    Endpoint(
        "GET",
        "/api/photos/{photo_id}/preview",
        preview,
        "Photoreal preview of selected elements (the render node's photoreal composite inside them)",
        ("element_ids",),
        returns="image/png",
    ),
    Endpoint(
        "GET",
        "/api/events",
        events,
        "Server-sent events: photo, registration, needs_anchor, overlay, ...",
        returns="text/event-stream",
    ),
    Endpoint("GET", "/api/openapi.json", openapi, "This document"),
)


def openapi_document() -> dict[str, Any]:
    paths: dict[str, dict[str, Any]] = {}
    for e in ENDPOINTS:
        op: dict[str, Any] = {
            "summary": e.summary,
            "parameters": [
                {"name": n, "in": "path", "required": True, "schema": {"type": "string"}} for n in _path_names(e.path)
            ]
            + [{"name": n, "in": "query", "schema": {"type": "string"}} for n in e.params],
            "responses": {
                "200": {"description": "OK", "content": {e.returns: {}}},
                "4XX": {"description": '{"error": reason}'},
            },
        }
        if e.body:
            op["requestBody"] = {"description": e.body, "content": {"application/json": {}}}
        paths.setdefault(e.path, {})[e.method.lower()] = op
    return {
        "openapi": "3.1.0",
        "info": {"title": "ConstructAide workbench", "version": "1"},
        "components": {"securitySchemes": {"token": {"type": "http", "scheme": "bearer"}}},
        "paths": paths,
    }


def _path_names(path: str) -> list[str]:
    return [p[1:-1] for p in path.split("/") if p.startswith("{")]


# ---------------------------------------------------------------------------------------------------- app


async def _api_error(req: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, ApiError)
    return JSONResponse({"error": exc.reason}, status_code=exc.status)


async def _http_error(req: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, HTTPException)
    return JSONResponse({"error": exc.detail}, status_code=exc.status_code)


class CrashGuard:
    """ASGI middleware: a bug in a handler becomes a JSON 500 (logged with its traceback, none sent) and the
    connection stays usable (Starlette's outermost error middleware would re-raise into the server)."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        started = False

        async def tracked(message: MutableMapping[str, Any]) -> None:
            nonlocal started
            started = started or message["type"] == "http.response.start"
            await send(message)

        try:
            await self.app(scope, receive, tracked)
        except Exception as exc:
            log.error("request %s %s failed", scope.get("method"), scope.get("path"), exc_info=exc)
            if scope["type"] != "http" or started:
                raise
            body = {"error": f"internal error: {type(exc).__name__}: {exc}"}
            await JSONResponse(body, status_code=500)(scope, receive, send)


class TokenGate:
    """ASGI middleware: with a token set, every request must carry it (``Authorization: Bearer``, ``?token=`` or
    the cookie the page gets), else 401."""

    def __init__(self, app: ASGIApp, token: str) -> None:
        self.app = app
        self.token = token

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or not self.token:
            await self.app(scope, receive, send)
            return
        req = Request(scope)
        given = req.query_params.get("token") or req.cookies.get(TOKEN_COOKIE) or ""
        auth = req.headers.get("authorization", "")
        if auth.lower().startswith("bearer "):
            given = auth[7:].strip()
        if not hmac.compare_digest(given.encode(), self.token.encode()):
            reason = (
                "access token required (Authorization: Bearer TOKEN or ?token=TOKEN)"
                if not given
                else ("wrong access token")
            )
            await JSONResponse({"error": reason}, status_code=401)(scope, receive, send)
            return
        await self.app(scope, receive, send)


def make_app(workbench: Workbench, token: str = "") -> Starlette:
    routes: list[Any] = [Route("/", index, methods=["GET"])]
    routes += [Route(e.path, e.handler, methods=[e.method]) for e in ENDPOINTS]
    routes.append(Mount("/static", app=StaticFiles(directory=STATIC), name="static"))
    app = Starlette(
        routes=routes,
        exception_handlers={ApiError: _api_error, HTTPException: _http_error},
    )
    app.state.workbench = workbench
    app.state.stopping = threading.Event()
    app.add_middleware(CrashGuard)
    app.add_middleware(TokenGate, token=token)
    return app


class HttpServer:
    """uvicorn serving ``app`` on its own thread; the socket is bound in the constructor (``port`` 0: any free
    port), so ``url`` is known and connections queue before the loop runs. A context manager."""

    def __init__(self, app: Starlette, host: str = "127.0.0.1", port: int = 0) -> None:
        self.app = app
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        self.sock = socket.socket(family, socket.SOCK_STREAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        # Accepted connections inherit it: a response written in two parts (head, body) must not wait for the
        # client's delayed ACK (Nagle).
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        try:
            self.sock.bind((host, port))
        except OSError as e:
            self.sock.close()
            raise OSError(f"cannot listen on {host}:{port}: {e.strerror}") from None
        self.sock.listen(128)
        self.host, self.port = host, int(self.sock.getsockname()[1])
        config = uvicorn.Config(app, log_level="warning", timeout_graceful_shutdown=2, lifespan="off")
        self.server = uvicorn.Server(config)
        self._thread = threading.Thread(target=self._run, name="workbench-http", daemon=True)

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}/"

    def _run(self) -> None:
        asyncio.run(self.server.serve(sockets=[self.sock]))

    def start(self) -> HttpServer:
        self._thread.start()
        return self

    def stop(self) -> None:
        self.app.state.stopping.set()
        self.server.should_exit = True
        if self._thread.is_alive():
            self._thread.join(timeout=10)
        self.sock.close()

    def __enter__(self) -> HttpServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

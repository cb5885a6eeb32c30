"""The page's web server: a small ASGI app (starlette, served by uvicorn) on a socket bound here, so that a port in
use is the user's error before anything starts (``bind``). ``/`` is the page, ``/static/`` its script and style
(in the package: nothing comes from the internet), ``/events`` the page pushed as Server-Sent Events, ``/page.json``
the latest page once, and ``/control`` (a replay only) pauses, plays, sets the rate or seeks.

Each browser's stream sends the board's latest page whenever it changed since the last it sent: a browser that
reads slowly skips the pages in between, and one that goes away only ends its own stream; the board is never
waited for and never waits (docs/view.md, "Safe and light")."""

from __future__ import annotations

import asyncio
import ipaddress
import signal
import socket
import threading
from importlib.resources import files

from .board import Board

STATIC = files(__package__) / "static"
POLL_S = 0.1  # how often a browser's stream looks for a newer page
KEEPALIVE_S = 15.0  # a comment line this often keeps an idle stream open through proxies
LOOPBACK = ("127.0.0.1", "::1", "localhost")


class BindError(ValueError):
    """The address cannot be served: one line for the user."""


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def bind(host: str, port: int) -> socket.socket:
    """A listening socket on ``host``:``port`` (0: a free port), or ``BindError``."""
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except socket.gaierror as exc:
        raise BindError(f"--host {host}: {exc.strerror}") from None
    family, _, _, _, address = infos[0]
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind(address)
        sock.listen(64)
    except OSError as exc:
        sock.close()
        raise BindError(f"cannot serve the page on {host}:{port}: {exc.strerror or exc}") from None
    sock.set_inheritable(True)
    return sock


def url_of(sock: socket.socket) -> str:
    host, port = sock.getsockname()[:2]
    return f"http://[{host}]:{port}/" if ":" in host else f"http://{host}:{port}/"


def app(board: Board, closing: threading.Event, control=None):
    """The ASGI app serving ``board``; ``control(pause=, rate=, seek=)`` for a replay (None: live, no control)."""
    from starlette.applications import Starlette  # noqa: PLC0415  (the extra 'view': only the view loads it)
    from starlette.requests import Request  # noqa: PLC0415
    from starlette.responses import FileResponse, JSONResponse, Response, StreamingResponse  # noqa: PLC0415
    from starlette.routing import Route  # noqa: PLC0415

    async def index(request: Request):
        return FileResponse(str(STATIC / "index.html"), headers={"Cache-Control": "no-store"})

    async def static(request: Request):
        name = request.path_params["name"]
        if name not in {p.name for p in STATIC.iterdir()}:  # only the package's own files, never a path
            return Response(status_code=404)
        return FileResponse(str(STATIC / name), headers={"Cache-Control": "no-store"})

    async def latest(request: Request):
        return Response(board.latest[1], media_type="application/json", headers={"Cache-Control": "no-store"})

    async def events(request: Request):
        async def stream():
            sent, idle = -1, 0.0
            while not closing.is_set():
                version, data = board.latest
                if version != sent:
                    sent, idle = version, 0.0
                    yield b"event: page\ndata: " + data + b"\n\n"
                elif idle >= KEEPALIVE_S:
                    idle = 0.0
                    yield b": keepalive\n\n"
                await asyncio.sleep(POLL_S)
                idle += POLL_S
        return StreamingResponse(stream(), media_type="text/event-stream",
                                 headers={"Cache-Control": "no-store", "X-Accel-Buffering": "no"})

    async def controlled(request: Request):
        if control is None:
            return JSONResponse({"error": "a live run cannot be controlled from the page"}, status_code=405)
        try:
            body = await request.json()
            pause = body.get("pause")
            rate = body.get("rate")
            seek = body.get("seek")
            if pause is not None and not isinstance(pause, bool):
                raise ValueError("pause: true or false")
            if rate is not None and not (isinstance(rate, (int, float)) and 0 < rate <= 10_000):
                raise ValueError("rate: a number in (0, 10000]")
            if seek is not None and not isinstance(seek, int):
                raise ValueError("seek: a mark's index")
            control(pause=pause, rate=None if rate is None else float(rate), seek=seek)
        except (ValueError, IndexError, AttributeError) as exc:
            return JSONResponse({"error": str(exc)}, status_code=400)
        return JSONResponse({"ok": True})

    return Starlette(routes=[Route("/", index), Route("/static/{name}", static), Route("/page.json", latest),
                             Route("/events", events), Route("/control", controlled, methods=["POST"])])


def serve(sock: socket.socket, asgi, closing: threading.Event) -> None:
    """Serve ``asgi`` on ``sock`` until SIGINT or SIGTERM (uvicorn's handlers); ``closing`` is set as it stops, so
    that the browsers' streams end."""
    import uvicorn  # noqa: PLC0415

    config = uvicorn.Config(asgi, log_level="warning", timeout_graceful_shutdown=2, lifespan="off")
    server = uvicorn.Server(config)
    original = server.handle_exit

    def handle_exit(sig, frame):
        closing.set()
        original(sig, frame)

    server.handle_exit = handle_exit
    # uvicorn raises the signal that stopped it again once it has stopped, with the handlers it found: these, so that
    # Ctrl-C or SIGTERM, the way to end a page, ends it with exit 0
    previous = {sig: signal.signal(sig, lambda *_: None) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        server.run(sockets=[sock])
    finally:
        closing.set()
        for sig, handler in previous.items():
            signal.signal(sig, handler)

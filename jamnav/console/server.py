"""``jamnav console``: the operator's console in a browser, served by aiohttp.

A thin shell around ``ConsoleState`` (what is known) and ``Feed`` (the bus): the page and its
scripts (``static/``), a small JSON API, and the frames pushed to each open page as
server-sent events, at most ``PUSH_HZ`` a second and only when something changed.

    GET  /                the page
    GET  /api/state       episode, step, uavs [{id, x, y, status, destination}], jammers,
                          map_version, ... and every UAV's trail this episode
    GET  /api/scenario    the area, the GBSs and the levels, to draw them
    GET  /api/map/<which> the ``served`` or the ``true`` coverage map, when drawn
    GET  /api/stream      the frames (text/event-stream)
    POST /api/jammer      {"x", "y", "power_w"} (with "add": true: one more), {"id", "x", "y"},
                          {"remove": ID} or {"off": true}: through the control topic

Safe by default: loopback only unless told, requests naming another host refused (a web
page elsewhere cannot reach it by DNS tricks), a POST only as JSON from the console's own
origin, and on a secure system the page and the API only with the token (401 otherwise).
"""

from __future__ import annotations

import asyncio
import hmac
import json
import socket
import sys
import threading
import time
from pathlib import Path
from typing import Any

from aiohttp import web

from jamnav.console.feed import Feed
from jamnav.console.listen import WebAddress
from jamnav.console.maps import CoverageMaps
from jamnav.console.state import ConsoleState, jammer_request
from shared import bus
from shared.access import Login
from shared.scenario import Scenario
from shared.topics import Topics

PUSH_HZ = 10
CATCH_UP_S = 1.0  # late ticks within this are made up; a longer stall is not
KEEPALIVE_S = 15.0  # a comment line now and then, so that proxies keep a quiet stream open
STATIC = Path(__file__).with_name("static")
ASSETS = {"console.js": "text/javascript", "console.css": "text/css"}
LOOPBACK_NAMES = ("127.0.0.1", "localhost", "[::1]")


def _error(status: int, text: str) -> web.Response:
    return web.json_response({"error": text}, status=status)


def _guard(token: str | None, hosts: set[str] | None):
    @web.middleware
    async def guard(request: web.Request, handler):
        if hosts is not None and request.host not in hosts:
            return _error(403, f"this console answers to {sorted(hosts)[0]} only")
        if token is not None and not request.path.startswith("/static/"):
            given = request.query.get("token") or request.headers.get(
                "Authorization", "").removeprefix("Bearer ")
            if not hmac.compare_digest(given.encode(), token.encode()):
                return _error(401, "this console needs its token: open the URL that jamnav "
                                   "printed (http://HOST:PORT/?token=...)")
        if request.method == "POST" and request.headers.get("Origin") not in (
                None, f"http://{request.host}"):
            return _error(403, "a command from another web page is refused")
        return await handler(request)

    return guard


def scenario_info(scenario: Scenario) -> dict[str, Any]:
    return {"name": scenario.name, "area": scenario.area.model_dump(),
            "gbs": scenario.gbs.positions, "levels": scenario.channel.level_count,
            "uav_radius_m": scenario.uav.radius_m, "jammer_power_w": scenario.jammer.power_w}


def _jammer_desk(feed: Feed):
    """``POST /api/jammer``: the body checked here, the command sent to the world."""

    async def api_jammer(request: web.Request) -> web.Response:
        if request.content_type != "application/json":
            return _error(415, "send JSON (Content-Type: application/json)")
        try:
            command = jammer_request(json.loads(await request.text()))
        except ValueError as exc:  # JSON errors included
            return _error(400, " ".join(str(exc).split()))
        except RecursionError:  # a few kB of nested brackets exhaust the JSON decoder's stack
            return _error(400, "JSON nested too deeply")
        try:
            reply = await asyncio.to_thread(feed.command, command)
        except bus.QueryRefused as exc:
            return _error(409, str(exc))
        except bus.BusError as exc:
            return _error(503, str(exc))
        if not reply.accepted:
            return web.json_response({"error": reply.reason, **reply.model_dump(mode="json")},
                                     status=409)
        return web.json_response(reply.model_dump(mode="json"))

    return api_jammer


def _frames(state: ConsoleState, stop: threading.Event):
    """``GET /api/stream``: a frame whenever the state changed, at most ``PUSH_HZ`` a
    second, until the page goes away or the console stops."""

    async def api_stream(request: web.Request) -> web.StreamResponse:
        response = web.StreamResponse(headers={"Content-Type": "text/event-stream",
                                               "Cache-Control": "no-cache"})
        await response.prepare(request)
        sent, tick = -1, time.monotonic()
        last_write = tick
        try:
            while not stop.is_set():
                revision, frame = state.encoded_frame()
                if revision != sent:
                    await response.write(b"data: " + frame + b"\n\n")
                    sent, last_write = revision, tick
                elif tick - last_write >= KEEPALIVE_S:
                    await response.write(b": keep-alive\n\n")
                    last_write = tick
                # Paced by the clock, not by sleeps after the work: PUSH_HZ on average, a
                # tick that came late made up at once; after a long stall, afresh from now.
                tick += 1 / PUSH_HZ
                if time.monotonic() - tick > CATCH_UP_S:
                    tick = time.monotonic()
                await asyncio.sleep(max(0.0, tick - time.monotonic()))
        except ConnectionError:  # the page went away
            pass
        return response

    return api_stream


def build_app(state: ConsoleState, feed: Feed, scenario: Scenario, stop: threading.Event,
              token: str | None = None, address: WebAddress | None = None) -> web.Application:
    """The console's web application. Its files are read now: an install without them fails
    at start, not at the first visit."""
    index = (STATIC / "index.html").read_bytes()
    assets = {name: (STATIC / name).read_bytes() for name in ASSETS}
    hosts = None if address is None or not address.loopback else {
        f"{name}:{address.port}" for name in LOOPBACK_NAMES}
    about = scenario_info(scenario)

    async def page(request: web.Request) -> web.Response:
        return web.Response(body=index, content_type="text/html")

    async def asset(request: web.Request) -> web.Response:
        name = request.match_info["name"]
        if name not in assets:
            raise web.HTTPNotFound()
        return web.Response(body=assets[name], content_type=ASSETS[name])

    async def api_state(request: web.Request) -> web.Response:
        return web.json_response(state.snapshot(trails=True))

    async def api_scenario(request: web.Request) -> web.Response:
        return web.json_response(about)

    async def api_map(request: web.Request) -> web.Response:
        payload = state.map_payload(request.match_info["which"])
        return _error(404, "no such map yet") if payload is None else web.json_response(payload)

    app = web.Application(middlewares=[_guard(token, hosts)])
    app.add_routes([web.get("/", page), web.get("/static/{name}", asset),
                    web.get("/api/state", api_state), web.get("/api/scenario", api_scenario),
                    web.get("/api/map/{which}", api_map),
                    web.get("/api/stream", _frames(state, stop)),
                    web.post("/api/jammer", _jammer_desk(feed))])
    return app


async def _serve(app: web.Application, listener: socket.socket, stop: threading.Event) -> None:
    runner = web.AppRunner(app, access_log=None, shutdown_timeout=1.0)
    await runner.setup()
    await web.SockSite(runner, listener).start()
    try:
        await asyncio.to_thread(stop.wait)
    finally:
        await runner.cleanup()


def serve(listener: socket.socket, address: WebAddress, endpoint: str, topics: Topics,
          scenario: Scenario, login: Login | None, token: str | None) -> int:
    """Run the console until SIGTERM or SIGINT: 0, or 1 when the router cannot be reached."""
    log = bus.setup_logging("console")
    with listener:
        session, stop = bus.service_session("console", endpoint, login)
        if session is None:
            return 1
        with session:
            state = ConsoleState()
            feed = Feed(session, topics, state, CoverageMaps(scenario), log)
            feed.start()
            worker = threading.Thread(target=feed.run, args=(stop,), name="console-feed")
            worker.start()
            try:
                app = build_app(state, feed, scenario, stop, token, address)
                print(f"jamnav console: {address.url(token)}", file=sys.stderr, flush=True)
                if not address.loopback and token is None:
                    print("jamnav console: warning: anyone who reaches this address can move "
                          "the jammer; a secure system (--credentials) needs a token",
                          file=sys.stderr, flush=True)
                asyncio.run(_serve(app, listener, stop))
            finally:
                stop.set()
                worker.join()
    return 0

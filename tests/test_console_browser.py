"""The console for real: ``jamnav up --secure`` serves it (on a free port, the default one held
here), its API refuses whoever lacks the token, and a headless Chromium driven by Playwright
loads the page, sees the UAVs move, places the jammer with a click, and then reads on the
timeline that the cloud detected the change and published a new map. Killed, the console is
restarted by the supervisor.

The browser is Debian's ``chromium`` (``make install`` installs it where it can); without it
the test fails, it never skips."""

from __future__ import annotations

import asyncio
import errno
import json
import os
import re
import signal
import socket
import stat
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path
from urllib.parse import parse_qs, urlsplit

from jamnav.cli import main as jamnav
from jamnav.console import listen
from tests import browser as chromium
from tests.support import free_endpoint, gone, wait_until


def http(url: str, body: dict | bytes | None = None) -> tuple[int, dict]:
    """(status, JSON body) of a GET, or of a POST of ``body`` as JSON (bytes: as they are)."""
    data = body if body is None or isinstance(body, bytes) else json.dumps(body).encode()
    request = urllib.request.Request(url, data=data,
                                     headers={"Content-Type": "application/json"})
    try:
        with urllib.request.urlopen(request, timeout=10) as response:
            return response.status, json.loads(response.read())
    except urllib.error.HTTPError as refused:
        return refused.code, json.loads(refused.read())


def console_pid(supervisor_pid: int) -> int:
    children = Path(f"/proc/{supervisor_pid}/task/{supervisor_pid}/children").read_text()
    return next(int(pid) for pid in children.split()
                if b"console" in Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0"))


def hold_default_port() -> socket.socket | None:
    """Hold the console's default port, as a second system on this machine would (None if
    one does already)."""
    try:
        return listen.bind(listen.parse_web(listen.DEFAULT_WEB))
    except OSError as exc:
        assert exc.errno == errno.EADDRINUSE
        return None


def test_the_console_shows_the_live_system_and_moves_the_jammer(supervisor, capsys, tmp_path):
    from playwright.sync_api import sync_playwright

    endpoint, run_dir = free_endpoint(), tmp_path / "run"
    held = hold_default_port()
    process = supervisor("--secure", "--uavs", "4", "--realtime", "--rate", "20",
                         "--no-jammer", "--map", "online", "--no-figures", "--endpoint",
                         endpoint, "--run-dir", str(run_dir), web=True)
    said: list[str] = []

    def listen_to_supervisor() -> None:
        for text in process.stderr:
            said.append(text)

    threading.Thread(target=listen_to_supervisor, daemon=True).start()
    try:
        line = wait_until(lambda: next((s for s in said if "console: http" in s), None), 60,
                          "the console's URL")
    finally:
        if held is not None:
            held.close()
    url = re.search(r"console: (\S+)", line).group(1)
    base, token = url.split("?")[0], parse_qs(urlsplit(url).query)["token"][0]
    if held is not None:  # else another system holds it, for how long no one knows
        assert urlsplit(url).port != listen.DEFAULT_PORT and "(port 8470 is in use)" in line
    token_file = run_dir / listen.TOKEN_FILE
    assert stat.S_IMODE(token_file.stat().st_mode) == 0o600
    assert token_file.read_text().strip() == token
    credentials = ["--credentials", str(run_dir / "credentials.json"), "--endpoint", endpoint]

    def jammer_in_force():
        """What the world says, not the console."""
        code = jamnav(["jammer", "show", *credentials])
        out = capsys.readouterr().out
        return json.loads(out)["jammers"] if code == 0 else "unknown"

    wait_until(lambda: http(f"{base}api/state?token={token}")[1]["episode"] is not None, 60,
               "the world's first state at the console")
    for path, body in (("", None), ("api/state", None), ("api/jammer", {"off": True}),
                       ("api/jammer", {"x": 0, "y": 0, "power_w": 5})):
        status, reply = http(f"{base}{path}", body)
        assert status == 401 and "token" in reply["error"]
    assert http(f"{base}api/jammer?token=wrong", {"x": 0, "y": 0, "power_w": 5})[0] == 401
    # A few kB of nested brackets exhaust the JSON decoder's stack: a 400, not a 500.
    status, reply = http(f"{base}api/jammer?token={token}", b"[" * 3000 + b"]" * 3000)
    assert status == 400 and reply["error"] == "JSON nested too deeply"
    assert jammer_in_force() == []

    with sync_playwright() as playwright:
        browser = chromium.launch(playwright)
        page = browser.new_page(viewport={"width": 1200, "height": 800})
        page.goto(url)
        page.wait_for_function("window.consoleStats.frames > 2 && window.consoleStats.maps > 0")
        canvas = page.locator("#map")
        before, positions = canvas.screenshot(), http(f"{base}api/state?token={token}")[1]
        time.sleep(1.0)
        after, moved = canvas.screenshot(), http(f"{base}api/state?token={token}")[1]
        assert before != after
        assert [(u["x"], u["y"]) for u in positions["uavs"]] != [
            (u["x"], u["y"]) for u in moved["uavs"]]
        assert len(moved["uavs"]) == 4 and moved["jammers"] == []

        page.fill("#power", "5")
        box = canvas.bounding_box()
        canvas.click(position={"x": box["width"] / 2, "y": box["height"] / 2})  # (0, 0)
        wait_until(lambda: http(f"{base}api/state?token={token}")[1]["jammers"] == [{
            "id": 0, "x": 0.0, "y": 0.0, "power_w": 5.0, "on": True, "path": None}], 10,
                   "the jammer at the console")
        assert jammer_in_force() == [{"id": 0, "x": 0.0, "y": 0.0, "power_w": 5.0,
                                      "height_m": 30.0, "path": None, "schedule": None}]
        page.wait_for_selector('#timeline li[data-kind="jammer_changed"]')
        page.wait_for_selector('#timeline li[data-kind="change_detected"]', timeout=30_000)
        published = page.wait_for_selector('#timeline li[data-kind="sinr_weights_published"]',
                                           timeout=60_000)
        version = int(re.search(r"SINR map v(\d+) published", published.inner_text()).group(1))
        assert version >= 1
        kinds = page.eval_on_selector_all("#timeline li", "items => items.map(i => i.dataset.kind)")
        # Newest first: the first detection after the click came before the first map after
        # it (the cloud may detect again while it refines the map, so the newest of each
        # need not be in that order).
        since_click = list(reversed(kinds[:kinds.index("jammer_changed")]))
        assert (since_click.index("change_detected")
                < since_click.index("sinr_weights_published"))
        # The map the cloud serves reaches that version; a later one (the estimate's, after a
        # provisional map) may already have replaced it by the time the page is read.
        page.wait_for_function(
            "Number((document.getElementById('served-version').textContent"
            f".match(/^\\(v(\\d+)\\)$/) || [])[1]) >= {version}")

        # A drag moves the jammer; a click elsewhere adds a second; its button removes it.
        centre_x, centre_y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
        page.mouse.move(centre_x, centre_y)
        page.mouse.down()
        page.mouse.move(centre_x + 40, centre_y - 40, steps=5)
        page.mouse.up()
        wait_until(lambda: [(j["x"] > 1, j["y"] > 1) for j in jammer_in_force()] == [
            (True, True)], 10, "the jammer dragged north-east")
        canvas.click(position={"x": box["width"] / 4, "y": box["height"] / 4})
        wait_until(lambda: [(j["id"], j["x"] < -1, j["y"] > 1) for j in jammer_in_force()][1:]
                   == [(1, True, True)], 10, "a second jammer north-west")
        page.click('#jammer-list li[data-id="1"] button')
        wait_until(lambda: [j["id"] for j in jammer_in_force()] == [0], 10,
                   "the second jammer removed")
        browser.close()

    # A console that dies is restarted like any child, at the same address, with the same
    # token.
    killed = console_pid(process.pid)
    os.kill(killed, signal.SIGKILL)
    wait_until(lambda: gone(killed), 10, "the console gone")

    def answers() -> bool:
        try:
            return http(f"{base}api/state?token={token}")[0] == 200
        except OSError:  # refused, reset or timed out while it starts again
            return False

    wait_until(answers, 60, "the console restarted")
    process.send_signal(signal.SIGINT)
    process.wait(60)
    report = json.loads((run_dir / "report.json").read_text())
    assert killed in [p["pid"] for p in report["processes"] if p["role"] == "console"]
    assert report["restarts"]["console"] == 1
    assert all(gone(p["pid"]) for p in report["processes"])


def test_the_panel_shows_the_jammers_counted_before_they_are_placed(scenario):
    """The page itself, fed by a console state with no bus: while a provisional map is in
    service it says how many jammers the cloud counted; then the estimate that places them,
    each jammer of the set with its id and a moving one with its velocity."""
    from playwright.sync_api import sync_playwright

    from jamnav.console.server import _serve, build_app
    from jamnav.console.state import ConsoleState
    from shared.events import SinrWeightsPublished
    from shared.jammer_messages import JammerEstimate

    def published(version: int, provisional: bool) -> SinrWeightsPublished:
        return SinrWeightsPublished(t=float(version), source="cloud", version=version,
                                    accuracy=0.9, sha256="0" * 64, path="m.safetensors",
                                    provisional=provisional, jammers_counted=2)

    state = ConsoleState()
    state.on_event(published(3, True))
    stop = threading.Event()
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen()
    app = build_app(state, None, scenario, stop)  # no jammer requests: no feed
    server = threading.Thread(target=lambda: asyncio.run(_serve(app, listener, stop)))
    server.start()
    text = "document.getElementById('estimate-text').textContent"
    try:
        with sync_playwright() as playwright:
            browser = chromium.launch(playwright)
            page = browser.new_page()
            page.goto(f"http://127.0.0.1:{listener.getsockname()[1]}/")
            page.wait_for_function(f"{text}.startsWith(\"Cloud's count\")")
            assert page.inner_text("#estimate-text") == (
                "Cloud's count: 2 jammers, not placed yet (provisional map)")
            state.on_estimate(JammerEstimate(
                map_version=4, t=4.0, present=True, x=-25.0, y=15.0, power_w=1.0,
                effective_power_dbm=10.0, sd_x_m=1.5, sd_y_m=2.0, sd_power_db=0.5,
                vx_mps=3.0, vy_mps=0.0, measurements=900,
                others=[JammerEstimate(map_version=4, t=4.0, present=True, id=1, x=25.0,
                                       y=-10.0, power_w=0.5, effective_power_dbm=7.0,
                                       sd_x_m=1.0, sd_y_m=1.0, sd_power_db=0.5,
                                       measurements=900)]))
            state.on_event(published(4, False))
            page.wait_for_function(f"{text}.startsWith(\"Cloud's estimate\")")
            assert page.inner_text("#estimate-text") == (
                "Cloud's estimate (map v4): 0: (-25.0 ± 1.5, 15.0 ± 2.0) m, 1.00 W, moving "
                "(3.0, 0.0) m/s; 1: (25.0 ± 1.0, -10.0 ± 1.0) m, 0.50 W")
            browser.close()
    finally:
        stop.set()
        server.join()

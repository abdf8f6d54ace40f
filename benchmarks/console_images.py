"""The two pictures of the operator's console (docs/images/console_*.png, docs/console.md),
taken in the headless Chromium the console's benchmark drives: a real-time run whose jammer is
swapped to (25, -10), 1 W, 25 s of flight in; its page once the cloud serves a map corrected by
an estimate of the swapped jammer, then with the true map shown instead.

    python -m benchmarks.console_images [--out docs/images]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

from benchmarks.bench_console import ROOT, console_url, free_port
from tests import browser as chromium

SWAP_TO = (25.0, -10.0, 1.0)
SWAP_AT_S = "25"
ESTIMATE_WITHIN_M = 10.0  # an estimate this close to the swapped jammer is the one to show
WAIT_S = 120.0
VIEWPORT = {"width": 1200, "height": 790}


def _state(url: str) -> dict:
    base = url.split("?")[0].rstrip("/")
    with urllib.request.urlopen(f"{base}/api/state", timeout=5) as reply:
        return json.load(reply)


def _estimate_of_swap(state: dict) -> bool:
    """The map in service is corrected by an estimate near the swapped jammer."""
    estimate, jammer = state.get("estimate"), state.get("jammer")
    return bool(
        jammer and (jammer["x"], jammer["y"]) == SWAP_TO[:2] and estimate and estimate["present"]
        and estimate["map_version"] == state["map_version"]
        and abs(estimate["x"] - SWAP_TO[0]) + abs(estimate["y"] - SWAP_TO[1]) < ESTIMATE_WITHIN_M)


def take(out: Path) -> list[Path]:
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as run_dir:
        argv = [sys.executable, "-m", "jamnav.cli", "up", "--uavs", "4", "--realtime",
                "--rate", "20", "--duration", "90", "--swap-jammer-at", SWAP_AT_S,
                "--swap-to", ",".join(f"{v:g}" for v in SWAP_TO), "--no-figures",
                "--endpoint", f"tcp/127.0.0.1:{free_port()}", "--run-dir", run_dir,
                "--web", f"127.0.0.1:{free_port()}"]
        process = subprocess.Popen(argv, cwd=ROOT, stdout=subprocess.DEVNULL,
                                   stderr=subprocess.PIPE, text=True)
        try:
            url = console_url(process)
            deadline = time.monotonic() + WAIT_S
            while not _estimate_of_swap(_state(url)):
                if time.monotonic() > deadline or process.poll() is not None:
                    raise RuntimeError("no map corrected by an estimate of the swapped jammer "
                                       f"within {WAIT_S:.0f} s")
                time.sleep(0.2)
            from playwright.sync_api import sync_playwright

            with sync_playwright() as playwright:
                browser = chromium.launch(playwright)
                page = browser.new_page(viewport=VIEWPORT)
                page.goto(url)
                page.wait_for_function("window.consoleStats.maps > 0 "
                                       "&& window.consoleStats.frames > 0", timeout=30_000)
                served = out / "console_served_map.png"
                page.screenshot(path=str(served))
                maps = page.evaluate("window.consoleStats.maps")
                page.check("input[name=coverage][value=true]")
                page.wait_for_function(f"window.consoleStats.maps > {maps}", timeout=30_000)
                truth = out / "console_true_map.png"
                page.screenshot(path=str(truth))
                browser.close()
        finally:
            process.terminate()
            process.wait(60)
    return [served, truth]


def main() -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.console_images",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "images")
    for path in take(parser.parse_args().out):
        print(f"wrote {path}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())

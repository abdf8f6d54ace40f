"""Helpers of the tests that run the system on the bus."""

from __future__ import annotations

import socket
import time
from pathlib import Path


def free_endpoint() -> str:
    """A loopback endpoint on a port nobody listens on now."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{probe.getsockname()[1]}"


def gone(pid: int) -> bool:
    """The process has exited (a zombie left for its parent to reap counts as exited)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0]
    except FileNotFoundError:
        return True
    return state == "Z"


def wait_until(condition, timeout: float, what: str = "a condition", every: float = 0.1):
    """The first truthy value of ``condition()``; AssertionError after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        time.sleep(every)
    raise AssertionError(f"timed out waiting for {what}")

"""Debian's chromium under Playwright, as the console's browser test and benchmark drive it.
Browsers that Playwright would download cannot be fetched here; ``make install`` installs
Debian's package where it may (as root)."""

from __future__ import annotations

from pathlib import Path

CHROMIUM = Path("/usr/bin/chromium")
ARGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
        "--disable-background-networking", "--disable-component-update", "--disable-sync"]


class BrowserMissing(RuntimeError):
    """No chromium to drive: a failure to report, never a reason to skip."""


def launch(playwright):
    """A headless chromium (Playwright's ``Browser``); BrowserMissing without one."""
    if not CHROMIUM.exists():
        raise BrowserMissing(f"{CHROMIUM} is missing: the console's browser test needs "
                             "Debian's chromium (as root: apt-get install chromium; "
                             "make install does it)")
    return playwright.chromium.launch(executable_path=str(CHROMIUM), args=ARGS)

"""What a process costs the machine, read from Linux's /proc."""

from __future__ import annotations

from pathlib import Path


def resident_mib(pid: int | str = "self") -> float | None:
    """Resident memory of process ``pid`` in MiB; None where it is gone or /proc is absent."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except (FileNotFoundError, ProcessLookupError):
        pass
    return None

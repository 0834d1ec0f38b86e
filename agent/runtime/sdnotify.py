"""Dependency-free ``sd_notify`` (systemd's service readiness and watchdog protocol).

One AF_UNIX datagram of newline-separated ``KEY=VALUE`` lines goes to ``$NOTIFY_SOCKET``; a
leading ``@`` names the abstract namespace. Without ``$NOTIFY_SOCKET`` (not started by systemd)
every call is a no-op returning ``False``; send errors are logged, never raised.
"""

from __future__ import annotations

import logging
import os
import socket
import time

log = logging.getLogger(__name__)


def _address() -> str | None:
    addr = os.environ.get("NOTIFY_SOCKET")
    if not addr:
        return None
    return "\0" + addr[1:] if addr[0] == "@" else addr


def notify(*lines: str) -> bool:
    """Send ``lines`` (e.g. ``"READY=1"``) in one datagram; ``True`` when sent."""
    addr = _address()
    if addr is None:
        return False
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as s:
            s.connect(addr)
            s.sendall("\n".join(lines).encode())
        return True
    except OSError as err:
        log.warning("sd_notify to %r failed: %s", os.environ.get("NOTIFY_SOCKET"), err)
        return False


def ready(status: str | None = None) -> bool:
    """``READY=1``: send once every source and sink is open (``Type=notify``)."""
    return notify("READY=1", *([f"STATUS={status}"] if status else []))


def status(text: str) -> bool:
    """``STATUS=``: one line shown by ``systemctl status``."""
    return notify(f"STATUS={text.splitlines()[0] if text else ''}")


def watchdog() -> bool:
    """``WATCHDOG=1``: ping from a place that proves progress, about every ``watchdog_interval() / 2``."""
    return notify("WATCHDOG=1")


def stopping(status: str | None = None) -> bool:
    return notify("STOPPING=1", *([f"STATUS={status}"] if status else []))


def reloading(status: str | None = None) -> bool:
    """``RELOADING=1`` (with ``MONOTONIC_USEC`` as systemd >= 253 wants); send ``ready()`` when done."""
    usec = time.clock_gettime_ns(time.CLOCK_MONOTONIC) // 1000
    return notify("RELOADING=1", f"MONOTONIC_USEC={usec}", *([f"STATUS={status}"] if status else []))


def watchdog_interval() -> float | None:
    """``WatchdogSec`` in seconds from ``$WATCHDOG_USEC``, or ``None`` when not enabled for this
    process (unset, not a positive integer, or ``$WATCHDOG_PID`` names another process)."""
    pid = os.environ.get("WATCHDOG_PID")
    if pid and pid != str(os.getpid()):
        return None
    try:
        usec = int(os.environ.get("WATCHDOG_USEC", ""))
    except ValueError:
        return None
    return usec / 1e6 if usec > 0 else None


class Watchdog:
    """Rate-limited ``WATCHDOG=1``: call :meth:`ping` on every pass of the loop that proves
    progress; a datagram goes out at most every ``fraction * WatchdogSec`` (none without a watchdog)."""

    def __init__(self, interval_s: float | None = None, fraction: float = 0.5):
        interval_s = watchdog_interval() if interval_s is None else interval_s
        self.period_s = None if not interval_s else interval_s * fraction
        self._last = float("-inf")

    @property
    def enabled(self) -> bool:
        return self.period_s is not None

    def ping(self) -> bool:
        """``True`` when a ping was sent now."""
        now = time.monotonic()
        if self.period_s is None or now - self._last < self.period_s:
            return False
        self._last = now
        return watchdog()

"""A virtual null-modem cable: two pseudo-terminals joined by a byte-copy thread.

Serial (RTU) tests open ``port_a`` on one side (e.g. the drive emulator) and ``port_b`` on the
other (the agent's client); bytes written to one come out of the other. ``unplug()`` drops
bytes in both directions (a cut cable) until ``plug()``. No timing is emulated: baud rate and
the RTU t3.5 gap mean nothing on a pty.

The slave ends stay open in this object (raw mode) so that a client closing and reopening its
port never makes the master side fail with EIO; the masters are non-blocking, and bytes that
the far side does not read (its pty buffer, about 4 KiB, is full) are dropped and counted.
"""

from __future__ import annotations

import errno
import logging
import os
import select
import threading
import tty

log = logging.getLogger(__name__)


class PtyNullModem:
    def __init__(self):
        self.port_a = self.port_b = ""
        self.dropped = 0  #: bytes dropped (unplugged or far side full)
        self.copied = 0
        self._fds: list[int] = []
        self._plugged = threading.Event()
        self._plugged.set()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def open(self) -> PtyNullModem:
        if self._thread is not None:
            return self
        ma, sa = os.openpty()
        mb, sb = os.openpty()
        self._fds = [ma, sa, mb, sb]
        for fd in (sa, sb):
            tty.setraw(fd)
        for fd in (ma, mb):
            os.set_blocking(fd, False)
        self.port_a, self.port_b = os.ttyname(sa), os.ttyname(sb)
        self._ma, self._mb = ma, mb
        self._stop.clear()
        self._thread = threading.Thread(target=self._copy, name="pty-null-modem", daemon=True)
        self._thread.start()
        return self

    def unplug(self) -> None:
        self._plugged.clear()

    def plug(self) -> None:
        self._plugged.set()

    def _copy(self) -> None:
        other = {self._ma: self._mb, self._mb: self._ma}
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select(list(other), [], [], 0.05)
            except (OSError, ValueError):
                return
            for fd in ready:
                try:
                    data = os.read(fd, 4096)
                except BlockingIOError:
                    continue
                except OSError as err:  # EIO: no slave open at the moment
                    if err.errno != errno.EIO:
                        log.debug("pty read: %s", err)
                    continue
                if not self._plugged.is_set():
                    self.dropped += len(data)
                    continue
                view = memoryview(data)
                while view:
                    try:
                        n = os.write(other[fd], view)
                    except (BlockingIOError, OSError):
                        self.dropped += len(view)
                        break
                    self.copied += n
                    view = view[n:]

    def close(self) -> None:
        """Stop the copy thread and close the ptys; safe twice."""
        if self._thread is not None:
            self._stop.set()
            self._thread.join(2.0)
            self._thread = None
        for fd in self._fds:
            try:
                os.close(fd)
            except OSError:
                pass
        self._fds = []

    def __enter__(self) -> PtyNullModem:
        return self.open()

    def __exit__(self, *exc) -> None:
        self.close()

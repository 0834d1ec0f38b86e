"""Pseudo-terminals as serial-port doubles (Linux/POSIX): a device end, a null-modem cable, a
hot-pluggable port.

* :class:`Pty`: ``os.openpty()`` in raw mode. Bytes written to ``master`` come out of the
  serial port at ``path`` (what ``serial.serial_for_url(path)`` opens) and the other way round.
  The pty keeps its own slave fd open so the master never sees EIO while no client is attached.
* :class:`NullModem`: two ptys joined by a byte-copy thread, so two programs that both open a
  serial *path* (a device emulator and the agent) talk to each other, like socat's pty pair;
  ``unplug()``/``plug()`` cut and restore the cable. :class:`PtyNullModem` is the variant the
  Modbus RTU tests use (opened by ``with``, ends ``port_a``/``port_b``, drops what the far side
  does not read).
* :class:`PluggablePort`: a stable symlink (like ``/dev/serial/by-id/...``) to a pty that can be
  unplugged (pty closed, link removed: the client's reads fail with EIO) and replugged (a new
  pty behind the same link).

A pty's buffer is small (about 4 KiB): write to it in chunks from a thread that does not also
read the other side (:func:`write_all` does the chunking with ``select``).
"""

from __future__ import annotations

import errno
import logging
import os
import select
import threading
import tty
from pathlib import Path

log = logging.getLogger(__name__)


def write_all(fd: int, data: bytes, stop: threading.Event | None = None, chunk: int = 256,
              poll_s: float = 0.05) -> int:
    """Write ``data`` to the non-blocking or blocking ``fd`` in ``chunk``-byte pieces, waiting for
    writability with ``select``; returns the bytes written (short only when ``stop`` was set).
    Raises ``OSError`` when the fd fails (e.g. EIO after the other end vanished)."""
    view = memoryview(data)
    done = 0
    while done < len(view):
        if stop is not None and stop.is_set():
            break
        _, w, _ = select.select([], [fd], [], poll_s)
        if not w:
            continue
        try:
            done += os.write(fd, view[done:done + chunk])
        except BlockingIOError:
            continue
    return done


class Pty:
    """A raw-mode pseudo-terminal: ``master`` fd (device side, non-blocking), serial ``path``."""

    def __init__(self) -> None:
        self.master, self._slave = os.openpty()
        tty.setraw(self._slave)  # before any client: no echo, no CR/LF translation, no line buffering
        os.set_blocking(self.master, False)
        self.path = os.ttyname(self._slave)
        self.closed = False

    def close(self) -> None:
        """Close both ends (safe twice): clients of ``path`` get EIO on their next read."""
        if self.closed:
            return
        self.closed = True
        for fd in (self.master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass

    def __enter__(self) -> Pty:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class NullModem:
    """Two ptys cross-connected by a copy thread: a client of ``path_a`` talks to one of ``path_b``.

    Opened on construction (``start=False``: by :meth:`open` or ``with``). ``unplug()`` drops
    bytes in both directions (a cut cable) until ``plug()``. When the far side does not read
    (its pty buffer is full) the copy waits for it, or with ``drop_when_full`` drops the bytes;
    dropped bytes are counted in :attr:`dropped`. No timing is emulated: baud rate and the RTU
    t3.5 gap mean nothing on a pty. Each pty keeps its slave end open (raw mode), so a client
    closing and reopening its port never makes the master side fail with EIO.
    """

    def __init__(self, chunk: int = 1024, *, drop_when_full: bool = False, start: bool = True) -> None:
        self.chunk = chunk
        self.drop_when_full = drop_when_full
        self.a: Pty | None = None
        self.b: Pty | None = None
        self.copied = 0  #: bytes copied
        self.dropped = 0  #: bytes dropped (unplugged, or far side full with ``drop_when_full``)
        self._plugged = threading.Event()
        self._plugged.set()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        if start:
            self.open()

    @property
    def path_a(self) -> str:
        return self.a.path if self.a is not None else ""

    @property
    def path_b(self) -> str:
        return self.b.path if self.b is not None else ""

    port_a, port_b = path_a, path_b

    @property
    def bytes_copied(self) -> int:
        return self.copied

    def open(self) -> NullModem:
        """Create the ptys and start copying (no-op when open)."""
        if self._thread is not None:
            return self
        self.a, self.b = Pty(), Pty()
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="null-modem", daemon=True)
        self._thread.start()
        return self

    def unplug(self) -> None:
        self._plugged.clear()

    def plug(self) -> None:
        self._plugged.set()

    def _run(self) -> None:
        peer = {self.a.master: self.b.master, self.b.master: self.a.master}
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select(list(peer), [], [], 0.05)
            except (OSError, ValueError):  # a pty was closed under us
                return
            for fd in ready:
                try:
                    data = os.read(fd, self.chunk)
                except BlockingIOError:
                    continue
                except OSError as err:  # EIO: no slave open at the moment
                    if err.errno != errno.EIO:
                        log.debug("pty read: %s", err)
                    continue
                if self._plugged.is_set():
                    self._forward(peer[fd], data)
                else:
                    self.dropped += len(data)

    def _forward(self, fd: int, data: bytes) -> None:
        if not self.drop_when_full:
            try:
                self.copied += write_all(fd, data, self._stop)
            except OSError:  # the far pty failed
                self.dropped += len(data)
            return
        view = memoryview(data)
        while view:
            try:
                n = os.write(fd, view)
            except OSError:  # BlockingIOError: far side full
                self.dropped += len(view)
                return
            self.copied += n
            view = view[n:]

    def close(self) -> None:
        """Stop the copy thread and close the ptys; safe twice."""
        if self._thread is not None:
            self._stop.set()
            self._thread.join(2.0)
            self._thread = None
        for p in (self.a, self.b):
            if p is not None:
                p.close()

    def __enter__(self) -> NullModem:
        return self.open()

    def __exit__(self, *exc) -> None:
        self.close()


class PtyNullModem(NullModem):
    """The null-modem cable of the serial (RTU) tests: opened by :meth:`open` (or ``with``),
    ends ``port_a`` (e.g. the drive emulator) and ``port_b`` (the agent's client); bytes the far
    side does not read are dropped and counted."""

    def __init__(self) -> None:
        super().__init__(4096, drop_when_full=True, start=False)


class PluggablePort:
    """A symlink ``link`` to a :class:`Pty` that can be unplugged and plugged in again."""

    def __init__(self, link: str | Path) -> None:
        self.link = Path(link)
        self.pty: Pty | None = None
        self.plug()

    @property
    def path(self) -> str:
        return str(self.link)

    @property
    def master(self) -> int:
        if self.pty is None:
            raise OSError("port is unplugged")
        return self.pty.master

    def plug(self) -> Pty:
        """A new pty behind ``link`` (unplugs the old one first)."""
        self.unplug()
        self.pty = Pty()
        tmp = self.link.with_name(self.link.name + ".tmp")
        tmp.unlink(missing_ok=True)
        tmp.symlink_to(self.pty.path)
        os.replace(tmp, self.link)
        return self.pty

    def unplug(self) -> None:
        self.link.unlink(missing_ok=True)
        if self.pty is not None:
            self.pty.close()
            self.pty = None

    close = unplug

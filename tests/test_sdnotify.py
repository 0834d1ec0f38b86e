"""sd_notify against a real AF_UNIX datagram socket (path and abstract namespace), watchdog interval."""

import os
import socket
import uuid

import pytest

from agent.runtime import sdnotify


@pytest.fixture(params=["path", "abstract"])
def notify_socket(request, tmp_path, monkeypatch):
    srv = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    if request.param == "path":
        addr = str(tmp_path / "notify.sock")
        srv.bind(addr)
    else:
        name = f"pmsm-test-{uuid.uuid4().hex}"
        srv.bind("\0" + name)
        addr = "@" + name
    srv.settimeout(2.0)
    monkeypatch.setenv("NOTIFY_SOCKET", addr)
    yield srv
    srv.close()


def test_messages_arrive_as_single_datagrams(notify_socket):
    assert sdnotify.ready("2 drives, zenoh open")
    assert notify_socket.recv(4096) == b"READY=1\nSTATUS=2 drives, zenoh open"
    assert sdnotify.status("monitoring\nsecond line dropped")
    assert notify_socket.recv(4096) == b"STATUS=monitoring"
    assert sdnotify.watchdog()
    assert notify_socket.recv(4096) == b"WATCHDOG=1"
    assert sdnotify.reloading()
    lines = notify_socket.recv(4096).decode().split("\n")
    assert lines[0] == "RELOADING=1" and lines[1].startswith("MONOTONIC_USEC=") and int(lines[1].split("=")[1]) > 0
    assert sdnotify.stopping()
    assert notify_socket.recv(4096) == b"STOPPING=1"


def test_without_systemd_is_a_quiet_noop(monkeypatch, tmp_path):
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    assert sdnotify.ready() is False
    monkeypatch.setenv("NOTIFY_SOCKET", str(tmp_path / "nobody-listens.sock"))
    assert sdnotify.watchdog() is False  # logged, never raised


@pytest.mark.parametrize("usec, pid, expect", [
    ("10000000", "self", 10.0), ("2500000", None, 2.5), ("10000000", "1", None),
    (None, None, None), ("0", None, None), ("garbage", None, None)])
def test_watchdog_interval(monkeypatch, usec, pid, expect):
    for key, value in (("WATCHDOG_USEC", usec), ("WATCHDOG_PID", str(os.getpid()) if pid == "self" else pid)):
        if value is None:
            monkeypatch.delenv(key, raising=False)
        else:
            monkeypatch.setenv(key, value)
    assert sdnotify.watchdog_interval() == expect


def test_watchdog_pings_are_rate_limited(notify_socket, monkeypatch):
    monkeypatch.setenv("WATCHDOG_USEC", "200000")
    monkeypatch.delenv("WATCHDOG_PID", raising=False)
    wd = sdnotify.Watchdog()
    assert wd.enabled and wd.period_s == pytest.approx(0.1)
    sent = sum(wd.ping() for _ in range(1000))  # a busy loop: one datagram, not a thousand
    assert sent == 1 and notify_socket.recv(4096) == b"WATCHDOG=1"
    monkeypatch.delenv("WATCHDOG_USEC")
    assert not sdnotify.Watchdog().enabled and not sdnotify.Watchdog().ping()

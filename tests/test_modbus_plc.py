"""The PLC's Modbus TCP server over real TCP (127.0.0.1, ephemeral ports): contract anchors,
heartbeat, one-publish state changes, consistent blocks, write guards, commands, and a
publish path that no client and no loop stall can block."""

import math
import socket
import struct
import threading
import time

import pytest
from pymodbus.client import ModbusTcpClient

from firmware_if import plc_registers as reg
from protocols.base import DriveStatus, Sink
from protocols.modbus_plc import PlcCommand, PlcModbusServer

pytestmark = pytest.mark.timeout(60)
DRIVES = ["gear", "chain", "spare"]


@pytest.fixture
def server():
    srv = PlcModbusServer(DRIVES, host="127.0.0.1", port=0, heartbeat_period_s=0.1)
    srv.open()
    yield srv
    srv.close()


@pytest.fixture
def plc(server):
    c = ModbusTcpClient("127.0.0.1", port=server.address[1], timeout=1, retries=0)
    assert c.connect()
    yield c
    c.close()


def ir(c, addr, n):
    rr = c.read_input_registers(addr, count=n, device_id=1)
    assert not rr.isError(), rr
    return rr.registers


def hr(c, addr, n=1):
    rr = c.read_holding_registers(addr, count=n, device_id=1)
    assert not rr.isError(), rr
    return rr.registers


def wait_for(pred, within=1.0, step=0.005):
    t_end = time.monotonic() + within
    while time.monotonic() < t_end:
        v = pred()
        if v:
            return v
        time.sleep(step)
    raise AssertionError("condition not met in time")


def status(drive="chain", **kw):
    kw.setdefault("quality", "good")
    return DriveStatus(drive=drive, **kw)


def test_sink_contract(server):
    assert isinstance(server, Sink)
    assert server.address[1] > 0


def test_global_registers_and_initial_blocks(plc):
    g = ir(plc, 0, 16)
    assert g[0] == reg.MAP_VERSION and g[2] == len(DRIVES)
    assert g[3] == 0 and g[4] == len(DRIVES)  # nobody published: summary normal, 3 drives not good
    assert g[10] == 100  # heartbeat period, ms
    assert abs(((g[6] << 16) | g[7]) - time.time()) < 5
    blocks = ir(plc, 16, 16 * len(DRIVES))  # all drive blocks in one request
    for i in range(len(DRIVES)):
        b = blocks[16 * i:16 * i + 16]
        assert b[0] == 0 and b[1] == reg.QUALITY_CODES["stale"]
        assert b[5] == 0xFFFF and b[6] == 0x8000 and b[7] == 65535  # FE, LOAD n/a; age saturated
    assert plc.read_input_registers(16 + 16 * len(DRIVES), count=1, device_id=1).exception_code == 2


def test_heartbeat_advances(plc):
    h0 = ir(plc, 1, 1)[0]
    time.sleep(0.45)
    h1 = ir(plc, 1, 1)[0]
    assert 2 <= (h1 - h0) % 65536 <= 6  # period 0.1 s


def test_default_heartbeat_at_least_once_a_second():
    with PlcModbusServer(["d"], port=0) as srv:
        c = ModbusTcpClient("127.0.0.1", port=srv.address[1], timeout=1, retries=0)
        assert c.connect()
        h0 = ir(c, 1, 1)[0]
        assert ir(c, 10, 1)[0] <= 1000
        wait_for(lambda: ir(c, 1, 1)[0] != h0, within=1.0, step=0.02)
        c.close()


def test_state_change_within_one_publish(server, plc):
    base = reg.address("STATE", 1)
    server.publish(status(state="warning", spectrum_state="warning", cluster_state="caution", fe_hz=50.0,
                          load_pct=-12.5, t=1_700_000_000.9, window=70_000, model="gear80",
                          peaks=[{"freq_hz": 123.45, "magnitude": 3.0, "th2": 1.5, "th3": 2.0},
                                 {"freq_hz": 80.0, "magnitude": 1.6, "th2": 1.0, "th3": 2.0}]))
    b = wait_for(lambda: (r := ir(plc, base, 16))[0] == 2 and r)
    assert b[1] == 0 and b[2] == 2 and b[3] == 1 and b[4] == 0
    assert b[5] == 5000 and b[6] == (-125) & 0xFFFF and b[7] < 1000
    assert (b[8] << 16 | b[9]) == 1_700_000_000 and (b[10] << 16 | b[11]) == 70_000
    assert b[12] == 1234 and b[13] == 200  # worst line: 123.45 Hz, ratio 2.0
    assert b[14] == reg.model_id("gear80") and b[15] == 1
    g = ir(plc, 0, 5)
    assert g[3] == 2 and g[4] == 2  # summary warning; two drives never updated
    # neighbours untouched
    assert ir(plc, reg.address("STATE", 0), 2) == [0, 3] and ir(plc, reg.address("STATE", 2), 2) == [0, 3]
    # back to normal with a NaN frequency
    server.publish(status(state="normal", fe_hz=math.nan, load_pct=math.nan, quality="stale"))
    b = wait_for(lambda: (r := ir(plc, base, 16))[0] == 0 and r)
    assert b[1] == 3 and b[5] == 0xFFFF and b[6] == 0x8000 and b[12:14] == [0, 0] and b[15] == 2


def test_data_age_grows_without_updates(server, plc):
    server.publish(status(state="normal"))
    assert server.flush()
    a0 = ir(plc, reg.address("DATA_AGE", 1), 1)[0]
    time.sleep(0.3)
    a1 = ir(plc, reg.address("DATA_AGE", 1), 1)[0]
    assert a0 < 150 and 300 - 100 <= a1 - a0 <= 600  # refreshed with each heartbeat (0.1 s here)


def test_blocks_are_never_torn(server, plc):
    """A reader hammering the block sees exactly one of the two published statuses."""
    a = status(state="caution", spectrum_state="caution", fe_hz=10.0, load_pct=10.0, t=1e9, window=1, model="a")
    b = status(state="warning", spectrum_state="warning", cluster_state="warning", fe_hz=99.0, load_pct=-99.0,
               t=2e9, window=2**31, model="b", peaks=[{"freq_hz": 7.0, "magnitude": 9.0, "th2": 3.0}])
    server.publish(a)
    assert server.flush()
    base = reg.address("STATE", 1)
    skip = {reg.BY_NAME[n].address for n in ("ALARM_ACKED", "DATA_AGE", "UPDATE_COUNT")}

    def key(regs):
        return tuple(v for k, v in enumerate(regs) if k not in skip)

    ka = key(ir(plc, base, 16))
    server.publish(b)
    assert server.flush()
    kb = key(ir(plc, base, 16))
    assert ka != kb
    stop = threading.Event()

    def publisher():
        k = 0
        while not stop.is_set():
            server.publish(a if k % 2 else b)
            k += 1
            time.sleep(0.0002)

    th = threading.Thread(target=publisher)
    th.start()
    try:
        seen = set()
        for _ in range(400):
            got = key(ir(plc, base, 16))
            assert got in (ka, kb)
            seen.add(got)
    finally:
        stop.set()
        th.join(5)
    assert seen == {ka, kb}


def test_writes_to_read_only_areas_get_exception_2(server, plc):
    assert plc.write_register(0, 1, device_id=1).exception_code == 2  # global HR: reserved
    assert plc.write_register(reg.drive_base(0) + 2, 1, device_id=1).exception_code == 2  # drive block reserved
    assert plc.write_registers(reg.address("RELEARN", 0), [0, 0], device_id=1).exception_code == 2  # spans reserved
    assert plc.write_register(16 + 16 * len(DRIVES), 1, device_id=1).exception_code == 2  # past the map
    assert plc.write_coil(0, True, device_id=1).exception_code == 2
    assert plc.read_coils(0, count=1, device_id=1).exception_code == 2
    assert plc.write_register(reg.address("ACK", 0), 2, device_id=1).exception_code == 3  # only 0/1
    assert server.stats.rejected_writes == 5  # the write past the map is refused by pymodbus itself
    assert server.commands() == []
    assert hr(plc, 0, 16 + 16 * len(DRIVES)) == [0] * (16 + 16 * len(DRIVES))


def test_acknowledge_alarm(server, plc):
    acked = reg.address("ALARM_ACKED", 1)
    server.publish(status(state="caution"))
    assert server.flush()
    assert ir(plc, acked, 1) == [0]
    assert not plc.write_register(reg.address("ACK", 1), 1, device_id=1).isError()
    wait_for(lambda: ir(plc, acked, 1) == [1])
    wait_for(lambda: hr(plc, reg.address("ACK", 1)) == [0])  # taken at once
    cmds = server.commands()
    assert [(c.drive, c.index, c.kind) for c in cmds] == [("chain", 1, "acknowledge")]
    assert isinstance(cmds[0], PlcCommand) and abs(cmds[0].t - time.time()) < 5
    server.publish(status(state="caution", window=2))  # same state: stays acknowledged
    assert server.flush() and ir(plc, acked, 1) == [1]
    server.publish(status(state="warning"))  # the alarm rose: needs a new acknowledgement
    assert server.flush() and ir(plc, acked, 1) == [0]
    plc.write_register(reg.address("ACK", 1), 1, device_id=1)
    wait_for(lambda: ir(plc, acked, 1) == [1])
    server.publish(status(state="normal"))
    assert server.flush() and ir(plc, acked, 1) == [0]
    server.publish(status(state="caution"))  # a new alarm after normal is not acknowledged
    assert server.flush() and ir(plc, acked, 1) == [0]


def test_relearn_request_handshake(server, plc):
    addr = reg.address("RELEARN", 2)
    assert not plc.write_register(addr, 1, device_id=1).isError()
    assert hr(plc, addr) == [1]  # pending until the agent takes it
    cmds = server.commands()
    assert [(c.drive, c.kind) for c in cmds] == [("spare", "relearn")]
    wait_for(lambda: hr(plc, addr) == [0])
    # FC16 over both command registers of drive 0
    assert not plc.write_registers(reg.address("ACK", 0), [1, 1], device_id=1).isError()
    assert sorted(c.kind for c in wait_for(server.commands)) == ["acknowledge", "relearn"]


def test_on_command_callback():
    got = []
    with PlcModbusServer(["a", "b"], port=0, on_command=got.append) as srv:
        c = ModbusTcpClient("127.0.0.1", port=srv.address[1], timeout=1, retries=0)
        assert c.connect()
        c.write_register(reg.address("RELEARN", 1), 1, device_id=1)
        wait_for(lambda: got)
        assert got[0].drive == "b" and got[0].kind == "relearn"
        wait_for(lambda: hr(c, reg.address("RELEARN", 1)) == [0])
        assert srv.commands() == []
        c.close()


def test_dead_clients_and_a_stalled_loop_never_block_publish(server, plc):
    # a client that pipelines requests and never reads the answers, and one that just sits there
    hog = socket.create_connection(server.address)
    idle = socket.create_connection(server.address)
    req = b"".join(struct.pack(">HHHBBHH", k & 0xFFFF, 0, 6, 1, 4, 0, 125) for k in range(3000))
    hog.setblocking(False)
    try:
        hog.send(req)
    except BlockingIOError:
        pass
    # and the server's loop itself busy for 0.5 s
    server._loop.call_soon(time.sleep, 0.5)
    worst = 0.0
    for k in range(2000):
        t = time.perf_counter()
        server.publish(status(state="caution" if k % 2 else "warning", window=k))
        worst = max(worst, time.perf_counter() - t)
    assert worst < 0.15, f"publish took {worst * 1e3:.1f} ms"  # far below the 0.5 s stall
    assert server.stats.coalesced > 0
    # the healthy PLC still sees the last update
    wait_for(lambda: (r := ir(plc, reg.address("STATE", 1), 12)) and (r[10] << 16 | r[11]) == 1999, within=3)
    h0 = ir(plc, 1, 1)[0]
    wait_for(lambda: ir(plc, 1, 1)[0] != h0, within=1)
    hog.close()
    idle.close()


def test_publish_never_raises(server):
    server.publish(status(drive="unknown"))
    server.publish(status(drive="chain", state="bogus"))
    assert server.stats.unknown_drive == 1 and server.stats.dropped == 1
    closed = PlcModbusServer(["x"], port=0)
    closed.publish(status(drive="x"))  # before open
    assert closed.stats.dropped == 1
    closed.open()
    closed.close()
    closed.publish(status(drive="x"))  # after close
    closed.close()
    assert closed.stats.dropped == 2


def test_open_on_a_busy_port_raises(server):
    other = PlcModbusServer(["x"], host="127.0.0.1", port=server.address[1])
    with pytest.raises(OSError):
        other.open()
    other.close()


def test_constructor_validation():
    with pytest.raises(ValueError):
        PlcModbusServer([])
    with pytest.raises(ValueError):
        PlcModbusServer(["a", "a"])
    with pytest.raises(ValueError):
        PlcModbusServer(["a"], heartbeat_period_s=2.0)


def test_evidence_block_says_why_and_how_close(server, plc):
    """Map version 2: drive i's evidence block at 4112 + 16 i carries the alarm's path and reason,
    the evidence per family (1.000 = caution threshold) and the learning progress."""
    assert ir(plc, 0, 1)[0] == 2
    reason = {"path": "gross", "feature": "gear_driven k=1", "families": ["gear_driven"],
              "freqs_hz": [87.5, 112.5], "z": 13.37, "threshold": 8.0}
    server.publish(status("chain", state="warning", extra={"reason": reason, "settling": False,
                                                           "evidence": {"gear_driven": 0.731, "cluster": 1.25}}))
    base = 4112 + 16 * DRIVES.index("chain")
    v = wait_for(lambda: (lambda d: d if d["ALARM_PATH"] == 1 else None)(reg.decode_evidence(ir(plc, base, 16))))
    assert v["REASON_FREQ"] == pytest.approx(87.5) and v["REASON_SCORE"] == pytest.approx(13.37)
    assert v["EVIDENCE_GEAR_DRIVEN"] == pytest.approx(0.731) and v["EVIDENCE_CLUSTER"] == pytest.approx(1.25)
    assert v["EVIDENCE_GEAR_DRIVING"] == 0 and v["LEARN_PROGRESS"] == 0
    assert ir(plc, reg.drive_base(DRIVES.index("chain")), 1)[0] == 2  # the drive block is unchanged
    server.publish(status("spare", quality="learning", extra={"learn_progress_pct": 42.3}))
    base = 4112 + 16 * DRIVES.index("spare")
    v = wait_for(lambda: (lambda d: d if d["LEARN_PROGRESS"] else None)(reg.decode_evidence(ir(plc, base, 16))))
    assert v["LEARN_PROGRESS"] == pytest.approx(42.3) and v["ALARM_PATH"] == 0
    rr = plc.read_input_registers(4112 + 16 * len(DRIVES), count=1, device_id=1)  # past the last block
    assert rr.isError() and rr.exception_code == 2

"""zenoh's access control on the plant's router (config/router-acl.json5, as shipped): every session
authenticates by user and password, and the router drops a command query from a user who may not
send commands before it reaches a gateway, even one signed with a valid key. All on loopback: one
``pmsm-agent router``, one gateway of ten drives, ``pmsm-agent fleet`` as three users."""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest

from agent.runtime.journal import Journal, journal_path
from runtime_support import ROOT, free_port, wait_for
from test_fleet import KEY_HEX, ROOT_PREFIX, Proc, fleet_cli, gateway_toml, write_keys, write_record

pytestmark = pytest.mark.timeout(120)

USERS = {"gw1": "gw-secret", "engineer": "eng-secret", "operator": "op-secret"}


def _client_config(path: Path, user: str, password: str) -> Path:
    path.write_text(json.dumps({"transport": {"auth": {"usrpwd": {"user": user, "password": password}},
                                              "link": {"tx": {"lease": 2000}}}}))
    path.chmod(0o600)
    return path


@pytest.fixture(scope="module")
def acl_plant(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("acl")
    users = tmp / "users.txt"
    users.write_text("".join(f"{u}:{p}\n" for u, p in USERS.items()))
    shipped = (ROOT / "config" / "router-acl.json5").read_text()
    assert "/etc/pmsm-router/users.txt" in shipped
    router_cfg = tmp / "router.json5"
    router_cfg.write_text(shipped.replace("/etc/pmsm-router/users.txt", str(users)))
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = Proc(["router", "--listen", endpoint, "--config", str(router_cfg)], tmp / "router.log")
    keys = write_keys(tmp / "keys.toml", KEY_HEX)
    gw_cfg = gateway_toml(tmp, "gw1", "s1", endpoint, write_record(tmp / "drive.npz"), keys, free_port())
    creds = _client_config(tmp / "gw1.json5", "gw1", USERS["gw1"])
    gw_cfg.write_text(gw_cfg.read_text().replace("[zenoh]\n", f'[zenoh]\nconfig_file = "{creds}"\n', 1))
    gateway = Proc(["run", "--config", str(gw_cfg)], tmp / "gw1.log")
    clients = {u: _client_config(tmp / f"{u}.json5", u, USERS[u]) for u in ("engineer", "operator")}
    try:
        router.start()
        wait_for(lambda: "listening on" in router.text(), 30, what="the router")
        gateway.start()

        def listed():
            r = fleet_cli(None, "status", "--connect", endpoint, "--zenoh-config", str(clients["operator"]),
                          "--inventory", str(tmp / "fleet.json"), "--json")
            return r.returncode == 0 and len(json.loads(r.stdout)["drives"]) == 10
        wait_for(listed, 60, 1.0, what="the gateway's ten drives in the fleet, asked as the operator")
        yield tmp, endpoint, keys, clients
    finally:
        gateway.stop()
        router.stop()
        for name in ("router", "gw1"):
            log = tmp / f"{name}.log"
            if log.exists():
                print(f"--- {name}.log (tail)\n" + "\n".join(log.read_text(errors="replace").splitlines()[-10:]))


def test_the_router_drops_commands_from_users_who_may_not_send_them(acl_plant):
    tmp, endpoint, keys, clients = acl_plant
    target = f"{ROOT_PREFIX}/s1/gw1/d3"

    def command(action: str, *who: str):
        return fleet_cli(None, "command", action, "--connect", endpoint, "--drive", target, "--role", "engineer",
                         "--key-file", str(keys), "--timeout", "2", *who)

    r = command("relearn", "--zenoh-config", str(clients["engineer"]), "--by", "engineer")
    assert r.returncode == 0 and "relearn accepted" in r.stdout, r.stderr
    # signed with the engineer's valid key, but sent by the operator's session: the router drops it
    r = command("acknowledge", "--zenoh-config", str(clients["operator"]), "--by", "operator")
    assert r.returncode == 2 and "no gateway answers" in r.stderr, (r.stdout, r.stderr)
    # no credentials at all: no session
    r = command("acknowledge")
    assert r.returncode == 2 and "no zenoh router answers" in r.stderr, r.stderr
    time.sleep(0.5)
    with Journal(journal_path(tmp / "gw1"), readonly=True) as j:
        events = [e for e in j.recent(None, kinds=["command"], limit=100) if e["drive"] == "d3"]
    assert [(e["detail"]["command"], e["detail"]["accepted"]) for e in events] == [("relearn", True)], events

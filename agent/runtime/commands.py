"""Signed commands over zenoh: ACK and RELEARN from an authorised role.

A command is the JSON payload of a query on ``<prefix>/<drive>/command``::

    {"command": "acknowledge" | "relearn", "target": "<prefix>/<drive>", "role": "operator",
     "by": "alice", "t": 1795000000.25, "nonce": "9f1c...", "mac": "<64 hex>"}

``mac`` is HMAC-SHA256 under the role's key over the other fields as canonical JSON (sorted
keys, no spaces). The agent accepts it when the role has a key, the MAC matches, the role is
allowed this command (``[commands]`` in the agent config), ``t`` is within ``max_skew_s`` of the
agent's clock, the nonce was not seen within the last ``2 * max_skew_s`` and ``target`` is the
drive the query reached (a command signed for one drive cannot be replayed on another). Anything
else is refused with the reason; the service counts and journals refusals.

Keys live in a TOML file ``[keys] <role> = "<hex, at least 16 bytes>"`` that is not
world-readable; the sender signs with the same file (``pmsm-agent fleet command``). Nonces are
kept in memory: a command captured in the last ``max_skew_s`` could be replayed once after an
agent restart (ACK and RELEARN repeated do no harm beyond a restarted learning).
"""

from __future__ import annotations

import hashlib
import hmac
import json
import os
import secrets
import stat
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from agent.errors import InputError, read_toml

COMMANDS = ("acknowledge", "relearn")
MIN_KEY_BYTES = 16
MAX_NONCES = 100_000  #: nonces remembered at most (a flood beyond this is refused, not remembered)
_FIELDS = ("command", "target", "role", "by", "t", "nonce")


class CommandRefused(PermissionError):
    """A command that is not executed; ``reason`` is one short phrase (also the counter's name)."""

    def __init__(self, reason: str, detail: str = ""):
        super().__init__(f"{reason}: {detail}" if detail else reason)
        self.reason = reason


@dataclass(frozen=True)
class Command:
    """An accepted command."""

    kind: str  #: "acknowledge" or "relearn"
    drive: str
    role: str
    by: str
    t: float  #: the sender's Unix time, s
    nonce: str


def load_keys(path: str | os.PathLike) -> dict[str, bytes]:
    """``{role: key}`` from the key file; ``InputError`` naming the file and the role."""
    path = Path(path)
    try:
        mode = path.stat().st_mode
    except OSError as err:
        raise InputError(f"cannot read the key file: {err.strerror}", source=str(path)) from None
    if mode & stat.S_IROTH:
        raise InputError("the key file is world-readable: chmod o-rwx (0600 or 0640)", source=str(path))
    doc = read_toml(path, "key file")
    keys = doc.get("keys")
    if not isinstance(keys, dict) or not keys:
        raise InputError("needs a [keys] table: <role> = \"<hex secret>\"", source=str(path))
    out = {}
    for role, text in keys.items():
        try:
            key = bytes.fromhex(text) if isinstance(text, str) else b""
        except ValueError:
            key = b""
        if len(key) < MIN_KEY_BYTES:
            raise InputError(f"keys.{role}: a hex string of at least {MIN_KEY_BYTES} bytes "
                             f"(e.g. python -c 'import secrets; print(secrets.token_hex(32))')", source=str(path))
        out[role] = key
    return out


def _mac(key: bytes, fields: Mapping) -> str:
    body = json.dumps({k: fields[k] for k in _FIELDS}, sort_keys=True, separators=(",", ":"))
    return hmac.new(key, body.encode(), hashlib.sha256).hexdigest()


def sign(command: str, target: str, role: str, key: bytes, *, by: str = "", t: float | None = None,
         nonce: str | None = None) -> dict:
    """A signed command document for ``target`` (``<prefix>/<drive>``)."""
    doc = {"command": command, "target": target, "role": role, "by": by,
           "t": time.time() if t is None else float(t), "nonce": nonce or secrets.token_hex(16)}
    doc["mac"] = _mac(key, doc)
    return doc


class CommandGate:
    """Checks signed commands (thread-safe). ``allowed``: ``{command: roles}``."""

    def __init__(self, keys: Mapping[str, bytes], allowed: Mapping[str, Sequence[str]], max_skew_s: float = 30.0,
                 clock: Callable[[], float] = time.time):
        self.keys, self.allowed = dict(keys), {c: tuple(r) for c, r in allowed.items()}
        self.max_skew_s, self.clock = float(max_skew_s), clock
        self._nonces: dict[str, float] = {}  #: nonce -> Unix time it may be forgotten
        self._lock = threading.Lock()

    @classmethod
    def from_config(cls, c) -> CommandGate:
        """From the agent config's ``[commands]`` table (``agent.runtime.config.CommandsCfg``)."""
        return cls(load_keys(c.key_file), {"acknowledge": c.acknowledge, "relearn": c.relearn}, c.max_skew_s)

    def check(self, drive: str, target: str, payload: str) -> Command:
        """The command in ``payload`` for ``drive`` (reached on ``target``), or ``CommandRefused``."""
        try:
            doc = json.loads(payload)
        except ValueError:
            raise CommandRefused("malformed", "not JSON") from None
        if not isinstance(doc, dict) or any(k not in doc for k in (*_FIELDS, "mac")):
            raise CommandRefused("malformed", f"needs the fields {', '.join(_FIELDS)}, mac")
        role, kind = str(doc["role"]), str(doc["command"])
        key = self.keys.get(role)
        if key is None:
            raise CommandRefused("unknown role", repr(role))
        try:
            good = hmac.compare_digest(_mac(key, doc), str(doc["mac"]))
        except (TypeError, ValueError):
            good = False
        if not good:
            raise CommandRefused("bad signature", f"role {role!r}")
        if kind not in COMMANDS:
            raise CommandRefused("unknown command", repr(kind))
        if role not in self.allowed.get(kind, ()):
            raise CommandRefused("role not allowed", f"{role!r} may not {kind}")
        if doc["target"] != target:
            raise CommandRefused("wrong target", f"signed for {doc['target']!r}, reached {target!r}")
        now = self.clock()
        try:
            t = float(doc["t"])
        except (TypeError, ValueError):
            raise CommandRefused("malformed", "t is not a number") from None
        if not abs(now - t) <= self.max_skew_s:
            raise CommandRefused("stale", f"t is {now - t:+.1f} s from the agent's clock "
                                 f"(at most {self.max_skew_s:g} s)")
        nonce = str(doc["nonce"])
        with self._lock:
            if len(self._nonces) > 1000:  # forget the expired ones now and then
                self._nonces = {n: until for n, until in self._nonces.items() if until >= now}
            if nonce in self._nonces:
                raise CommandRefused("replayed", f"nonce {nonce[:16]} was used already")
            if len(self._nonces) >= MAX_NONCES:
                raise CommandRefused("busy", "too many commands within the replay window")
            self._nonces[nonce] = now + 2 * self.max_skew_s
        return Command(kind, drive, role, str(doc["by"]), t, nonce)

"""Teleop: joint targets from a leader arm over UDP, only from the leader, authenticated and replay-proof.

Datagram (little-endian, `datagram()` makes one): `b"SKT2"`, u64 stamp (the leader's wall clock in
microseconds since the Unix epoch, strictly increasing from one datagram to the next), u16 joint count n,
n float64 joint targets (rad) in the robot's joint order, then 32 bytes: HMAC-SHA256 of everything before
it under the shared key (`skinsafe teleop-key FILE` makes one; without a key, loopback only, the HMAC is
under the empty key: it catches corruption, it authenticates nothing).

The receiver (`Teleop`) takes a datagram's targets only when, in this order:
1. it comes from the leader: `--teleop-leader HOST[:PORT]` names it, or the first sender whose datagram
   passes 2-5 is pinned (its address and port) for the rest of the run;
2. its length, magic and joint count are right;
3. its HMAC is right (`hmac.compare_digest`);
4. its stamp is within `SKEW_S` of this computer's wall clock (a capture replayed from another session, or
   a leader whose clock is not synchronised);
5. its stamp is after the newest accepted (a replay or a reordered datagram) and at most the command
   timeout + `JUMP_MARGIN_S` after it (a datagram far ahead is refused, never taken as the newest: the
   stamps of a leader that is on time never jump further, as the run stops once it is silent that long).
Every other datagram is refused, counted per sender (address:port) with the first reason, and never
moves the robot. `INTRUDER_DATAGRAMS` refused within `INTRUDER_WINDOW_S` is an intrusion (`intrusion`),
which the monitor turns into a protective stop (`command-intruder`): the leader's datagrams could still
be told apart, but the operator's picture of who talks to the robot is wrong (a second leader aimed at
this robot, a leader with another key, a replayed capture, an attacker) and a person must look before it
moves again. A non-finite target in an authenticated datagram stops the robot (`StopRobot`). At most
`PER_TICK` datagrams are read per tick: a flood cannot hold the loop (the rest wait in the socket). What queued before the robot
moves (the leader streaming while the run was wired) is dropped unread at `start`.

Key file (`make_key`, `load_key`): JSON `{"schema_version": 1, "kind": "skinsafe-teleop-key", "key": 64 hex}`,
written atomically with mode 0600 and refused when others may read it. A record keeps the key's path and
`key_id` (a SHA-256 of the key, not the key).
"""
from __future__ import annotations

import collections
import hashlib
import hmac
import ipaddress
import json
import secrets
import socket
import struct
import time
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path

import numpy as np

from skinsafe.core.runtime.commands import CommandError, Hold
from skinsafe.core.runtime.protocol import StopRobot
from skinsafe.core.safety.stack import TrajectorySource
from skinsafe.core.skin.files import atomic_write

MAGIC = b"SKT2"
HEAD = struct.Struct("<4sQH")
TAG_BYTES = 32  # HMAC-SHA256
KEY_BYTES = 32
KEY_SCHEMA = 1
KEY_KIND = "skinsafe-teleop-key"
SKEW_S = 1.0  # a stamp within this of the receiver's wall clock (the two computers' clocks synchronised: NTP)
JUMP_MARGIN_S = 0.5  # a stamp at most the command timeout + this after the newest
INTRUDER_DATAGRAMS = 3  # refused datagrams within INTRUDER_WINDOW_S that stop the robot
INTRUDER_WINDOW_S = 1.0
PER_TICK = 64  # datagrams read per tick at most
DRAIN_MAX = 100_000  # datagrams queued before the robot moves, dropped unread at the start (bounded: a flood)
MAX_SENDERS = 32  # refused senders tallied by name; more are counted together as "others"


class Refusal(str, Enum):
    """Why a datagram was refused (module docstring, in the order checked)."""

    NOT_LEADER = "not the leader"
    MALFORMED = "malformed"
    FORGED = "fails authentication"
    CLOCK = "stamped off this computer's clock"
    REPLAYED = "replayed"
    JUMPED = "jumped ahead"


@dataclass(frozen=True)
class TeleopKey:
    """A shared key: where it came from and the secret (never printed nor recorded: `key_id` is)."""

    path: str
    secret: bytes = field(repr=False)

    @property
    def key_id(self) -> str:
        return hashlib.sha256(b"skinsafe teleop key id\0" + self.secret).hexdigest()[:16] if self.secret else ""


NO_KEY = TeleopKey("", b"")


def make_key(path: str | Path, force: bool = False) -> TeleopKey:
    """A fresh random key written to `path` (mode 0600, atomically); an existing file only with `force`."""
    path = Path(path)
    if path.exists() and not force:
        raise CommandError(f"{path}: exists; a new key locks out every leader holding the old one: pass --force to "
                           "replace it, or give another path")
    secret = secrets.token_bytes(KEY_BYTES)
    text = json.dumps({"schema_version": KEY_SCHEMA, "kind": KEY_KIND, "key": secret.hex()}) + "\n"
    atomic_write(path, text, permissions=0o600)  # mkstemp makes it 0600 before a byte of the key is in it
    return TeleopKey(str(path), secret)


def load_key(path: str | Path) -> TeleopKey:
    """The key in `path`, or CommandError naming the file, the field and the fix."""
    path = Path(path)
    fix = f"make one with `skinsafe teleop-key {path}`"
    try:
        mode = path.stat().st_mode
        raw = path.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise CommandError(f"teleop key {path}: cannot read it ({getattr(e, 'strerror', None) or e}); {fix}") from None
    if mode & 0o077:
        raise CommandError(f"teleop key {path}: others may read it (mode {mode & 0o777:o}); `chmod 600 {path}`")
    try:
        doc = json.loads(raw)
    except ValueError:
        raise CommandError(f"teleop key {path}: not JSON; {fix}") from None
    if not isinstance(doc, dict) or doc.get("kind") != KEY_KIND:
        raise CommandError(f"teleop key {path}: 'kind' is not {KEY_KIND!r}; {fix}")
    if doc.get("schema_version") != KEY_SCHEMA:
        raise CommandError(f"teleop key {path}: schema_version {doc.get('schema_version')!r}; this skinsafe reads "
                           f"{KEY_SCHEMA}: {fix}")
    try:
        secret = bytes.fromhex(doc["key"])
    except (KeyError, TypeError, ValueError):
        secret = b""
    if len(secret) != KEY_BYTES:
        raise CommandError(f"teleop key {path}: 'key' is not {KEY_BYTES} bytes of hex; {fix}")
    return TeleopKey(str(path), secret)


def now_us() -> int:
    """This computer's wall clock, microseconds since the Unix epoch (a datagram's stamp)."""
    return time.time_ns() // 1000


def datagram(targets, key: TeleopKey, stamp_us: int) -> bytes:
    """One signed datagram (module docstring)."""
    q = np.asarray(targets, dtype="<f8").ravel()
    body = HEAD.pack(MAGIC, stamp_us & 0xFFFF_FFFF_FFFF_FFFF, len(q)) + q.tobytes()
    return body + hmac.new(key.secret, body, hashlib.sha256).digest()


class Stamper:
    """Strictly increasing stamps from the wall clock (two datagrams in one microsecond: the second one later)."""

    def __init__(self):
        self.last = 0

    def __call__(self) -> int:
        self.last = max(now_us(), self.last + 1)
        return self.last


@dataclass(frozen=True)
class Sender:
    """A sender whose datagrams were refused: how many, and why the first was."""

    address: str  # host:port ("others" past MAX_SENDERS)
    datagrams: int
    why: Refusal
    first: float  # host time.monotonic() of its first


@dataclass(frozen=True)
class Intrusion:
    """INTRUDER_DATAGRAMS refused within INTRUDER_WINDOW_S: who sent them, and the first's arrival (the onset)."""

    senders: tuple[Sender, ...]
    datagrams: int
    onset: float
    leader: str  # "" while none is pinned
    key_id: str

    @property
    def message(self) -> str:
        named = ", ".join(f"{s.address} ({s.datagrams}, {s.why.value})" for s in self.senders)
        head = f"command: teleop: {self.datagrams} datagrams refused within {INTRUDER_WINDOW_S:g} s from {named}"
        if not self.leader and all(s.why is Refusal.FORGED for s in self.senders):
            return (f"{head} and none accepted: a leader signing with another key (this run's key id "
                    f"{self.key_id or 'none: no --teleop-key'}); give the leader this run's key file")
        return f"{head}; the leader is {self.leader or 'not yet pinned'}: protective stop, see who else sends"


def _name(address) -> str:
    return f"{address[0]}:{address[1]}"


def _host(text: str, what: str) -> str:
    """An IPv4 address for `text` (a name is resolved once, here)."""
    try:
        return socket.gethostbyname(text)
    except OSError as e:
        raise CommandError(f"{what}: {text!r} is not an address this computer can resolve ({e})") from None


class Teleop(Hold):
    """Joint targets over UDP from the leader alone (module docstring), tracked; `age()` since the last accepted
    datagram. `clock_us`: this computer's wall clock in µs (a test seam; default `now_us`)."""

    def __init__(self, address: str, joint_names: list[str], limits: dict[str, np.ndarray], stale_s: float = 0.1,
                 key: TeleopKey = NO_KEY, leader: str | None = None, clock_us=now_us):
        super().__init__(len(joint_names))
        host, _, port = address.rpartition(":")
        try:
            port = int(port)
            if not 0 <= port <= 65535:
                raise ValueError
        except ValueError:
            raise CommandError(f"teleop:{address}: give a UDP port 0..65535, e.g. teleop:9870 or "
                               "teleop:127.0.0.1:9870") from None
        self.limits, self.stale_s, self.key, self.clock_us = limits, float(stale_s), key, clock_us
        self.leader = self._leader(leader) if leader else None  # (host, port or None)
        self.pinned = "given" if leader else "first datagram"
        bind = _host(host, f"teleop:{address}") if host else "127.0.0.1"
        if not ipaddress.ip_address(bind).is_loopback and not key.secret:
            raise CommandError(f"teleop:{address}: listening on {bind}, beyond this computer, without a key lets "
                               "anyone who reaches the port drive the robot; make one with `skinsafe teleop-key FILE`, "
                               "give it to the leader and pass --teleop-key FILE")
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self.sock.bind((bind, port))
        except OSError as e:
            self.sock.close()
            raise CommandError(f"teleop:{address}: cannot listen there ({e}); choose a free port") from None
        self.sock.setblocking(False)
        self.port = self.sock.getsockname()[1]
        self.spec = f"teleop:{bind}:{self.port}"
        self.size = HEAD.size + 8 * len(joint_names) + TAG_BYTES
        self.jump_us = int((self.stale_s + JUMP_MARGIN_S) * 1e6)
        self.target = None
        self.stamp = None  # the newest accepted stamp
        self.last = None  # host time of the last accepted datagram
        self.accepted = self.refused = self.dropped = 0
        self.senders: dict[str, Sender] = {}
        self.recent: collections.deque = collections.deque(maxlen=INTRUDER_DATAGRAMS)  # (mono, sender) refused
        self.intrusion: Intrusion | None = None
        self.track = TrajectorySource(lambda t: (self.target, self.zero))

    @staticmethod
    def _leader(text: str) -> tuple[str, int | None]:
        host, sep, port = text.rpartition(":")
        host, port = (host, port) if sep else (text, "")
        try:
            p = int(port) if port else None
            if p is not None and not 0 < p <= 65535:
                raise ValueError
        except ValueError:
            raise CommandError(f"--teleop-leader {text}: give HOST or HOST:PORT (a port 1..65535)") from None
        return _host(host, f"--teleop-leader {text}"), p

    @property
    def leader_name(self) -> str:
        if self.leader is None:
            return ""
        return self.leader[0] if self.leader[1] is None else _name(self.leader)

    def _receive(self) -> None:
        for _ in range(PER_TICK):
            try:
                data, sender = self.sock.recvfrom(65536)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:  # e.g. an ICMP port-unreachable echo: no datagram, nobody to name
                continue
            now = time.monotonic()
            why = self._judge(data, sender)
            if why is not None:
                self._refuse(_name(sender), why, now)
                continue
            _, stamp, n = HEAD.unpack_from(data)
            q = np.frombuffer(data, "<f8", n, HEAD.size).astype(float)
            if not np.isfinite(q).all():
                raise StopRobot(f"command: teleop datagram {stamp} from {_name(sender)} holds a non-finite joint "
                                "target")
            if self.leader is None or self.leader[1] is None:
                self.leader = (sender[0], sender[1])  # pinned: its address and port for the rest of the run
            self.target = np.clip(q, self.limits["q_min"], self.limits["q_max"])
            self.stamp, self.last = stamp, now
            self.accepted += 1

    def _judge(self, data: bytes, sender) -> Refusal | None:
        """Why this datagram is refused (module docstring's order), or None."""
        if self.leader is not None and (sender[0] != self.leader[0] or self.leader[1] not in (None, sender[1])):
            return Refusal.NOT_LEADER
        if len(data) != self.size or data[:4] != MAGIC or HEAD.unpack_from(data)[2] != len(self.zero):
            return Refusal.MALFORMED
        body, tag = data[:-TAG_BYTES], data[-TAG_BYTES:]
        if not hmac.compare_digest(tag, hmac.new(self.key.secret, body, hashlib.sha256).digest()):
            return Refusal.FORGED
        stamp = HEAD.unpack_from(data)[1]
        if abs(stamp - self.clock_us()) > SKEW_S * 1e6:
            return Refusal.CLOCK
        if self.stamp is not None and stamp <= self.stamp:
            return Refusal.REPLAYED
        if self.stamp is not None and stamp - self.stamp > self.jump_us:
            return Refusal.JUMPED
        return None

    def _refuse(self, name: str, why: Refusal, now: float) -> None:
        self.refused += 1
        if name not in self.senders and len(self.senders) >= MAX_SENDERS:
            name = "others"
        s = self.senders.get(name)
        self.senders[name] = Sender(name, 1, why, now) if s is None else Sender(name, s.datagrams + 1, s.why, s.first)
        self.recent.append((now, name))
        if (self.intrusion is None and len(self.recent) == INTRUDER_DATAGRAMS
                and now - self.recent[0][0] <= INTRUDER_WINDOW_S):
            names = dict.fromkeys(n for _, n in self.recent)
            self.intrusion = Intrusion(tuple(self.senders[n] for n in names), INTRUDER_DATAGRAMS, self.recent[0][0],
                                       self.leader_name, self.key.key_id)

    def start(self, q0: np.ndarray) -> None:
        """The robot is about to move: what queued while the run was wired (the pre-flight, the warm-up: seconds of
        a leader's datagrams, stale by now) is dropped unread; the leader's next datagram is the first."""
        self.dropped = 0
        for _ in range(DRAIN_MAX):
            try:
                self.sock.recv(65536)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                continue
            self.dropped += 1

    def __call__(self, t: float, q: np.ndarray) -> np.ndarray:
        self._receive()
        return self.zero if self.target is None else self.track(t, q)

    def age(self) -> float:
        return 0.0 if self.last is None else time.monotonic() - self.last

    def summary(self) -> dict:
        """Who drove the robot and who was refused (the run's report, stats and record)."""
        return {"leader": self.leader_name, "pinned": self.pinned, "accepted": self.accepted, "refused": self.refused,
                "key": self.key.path, "key_id": self.key.key_id,
                "senders": [{"address": s.address, "datagrams": s.datagrams, "why": s.why.value}
                            for s in self.senders.values()]}

    def close(self) -> None:
        self.sock.close()

"""Deploy a taxel map to its boards: find them, push each board's config, commit, read back, compare hashes.

Every board either ends up running the new config (verified by reading it back) or keeps its old
one; a board that fails is reported with the reason and with what it runs afterwards.
"""
from __future__ import annotations

import glob
import hashlib
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

from skinsafe.core.skin.model import Board, SkinDesign
from skinsafe.hardware import protocol as P
from skinsafe.hardware.board_config import BoardConfig, board_configs, diff
from skinsafe.hardware.client import BoardClient, BoardError


@dataclass
class BoardReport:
    """The outcome for one board; `active_hash` is what the board runs afterwards (None: unknown)."""

    board: Board
    port: str | None
    status: str  # updated | unchanged | would-update | refused | failed | missing
    message: str = ""
    old_hash: bytes | None = None
    new_hash: bytes | None = None
    active_hash: bytes | None = None
    changes: dict | None = None
    tx_bytes: int = 0
    rx_bytes: int = 0
    wire_s: float = 0.0
    seconds: float = 0.0
    resent: int = 0

    @property
    def ok(self) -> bool:
        return self.status in ("updated", "unchanged", "would-update")

    def line(self) -> str:
        b = self.board
        head = f"board {b.id} '{b.name}' uid {b.uid:#x}" + (f" on {self.port}" if self.port else "")
        h = lambda x: x.hex()[:8] if x else "none"  # noqa: E731
        out = f"{head}: {self.status}"
        if self.status in ("updated", "unchanged", "would-update"):
            out += f" ({h(self.old_hash)} -> {h(self.new_hash)}"
            if self.changes is not None:
                out += ", channels +{added} -{removed} ~{changed}".format(**self.changes)
            out += f", {self.tx_bytes + self.rx_bytes} B, {self.seconds:.2f} s, wire {self.wire_s:.2f} s"
            out += f", {self.resent} resent)"
        if self.message:
            out += f": {self.message}"
        return out


def check_compatible(info: P.Identity, cfg: BoardConfig, board: Board, port: str) -> str | None:
    """Why this board must not get this config (None if it may): checked before any config byte is sent."""
    if info.uid != cfg.uid:
        return (f"{port} holds board uid {info.uid:#x}, the map's board '{board.name}' is uid {cfg.uid:#x}; "
                "connect the right board or use --all to match boards by uid")
    if info.firmware[0] != P.FIRMWARE_MAJOR:
        return (f"firmware {info.firmware_str} is not supported (this host needs {P.FIRMWARE_MAJOR}.x); "
                "update the board firmware")
    if info.n_channels != cfg.capacity:
        return (f"the board has {info.n_channels} channels, the map's board '{board.name}' has capacity "
                f"{cfg.capacity}; fix the board's capacity in the design or connect the right board")
    if not info.capabilities & P.CAP_READBACK:
        return "the board cannot read its config back; update the board firmware"
    return None


def deploy_board(cfg: BoardConfig, board: Board, port: str, dry_run: bool = False, force: bool = False,
                 verify: str = "readback", **client_kw) -> BoardReport:
    """Push one board's config over `port` and verify it; never raises for board or link trouble.

    verify "readback": read the whole config back and hash it here; "hash": the board hashes its flash.
    """
    if verify not in ("readback", "hash"):
        raise ValueError(f"verify={verify!r}: use 'readback' or 'hash'")
    t0 = time.monotonic()
    data, digest = cfg.to_bytes(), cfg.sha256
    rep = BoardReport(board, port, "failed", new_hash=digest)
    client, sent = None, False
    try:
        client = BoardClient(port, **client_kw)
        info = client.identify()
        rep.old_hash = info.config_hash if info.flags & P.FLAG_CONFIG_VALID else None
        why = check_compatible(info, cfg, board, port)
        if why:
            rep.status, rep.message, rep.active_hash = "refused", why, rep.old_hash
            return rep
        client.uid = info.uid  # from now on, address this board only
        if dry_run:
            old = None
            if rep.old_hash is not None:
                old = BoardConfig.from_bytes(client.read_config(info.config_length), f"board {info.uid:#x}")
            rep.changes = diff(old, cfg)
            rep.status = "unchanged" if rep.old_hash == digest else "would-update"
            rep.active_hash = rep.old_hash
            return rep
        if rep.old_hash == digest and not force:
            rep.status, rep.active_hash = "unchanged", digest
            return rep
        sent = True
        client.write_config(data, digest)
        if verify == "hash":
            rep.active_hash = client.flash_hash()
        else:
            rep.active_hash = hashlib.sha256(client.read_config(len(data))).digest()
        if rep.active_hash != digest:
            rep.message = f"the config in the board's flash differs from the one sent ({verify}); deploy again"
            return rep
        rep.status = "updated"
        return rep
    except BoardError as e:
        rep.message = str(e)
        if not sent:
            rep.active_hash = rep.old_hash
            rep.message += "; no config was sent, so the board keeps the one it had"
        else:
            rep.active_hash = _probe(port, cfg.uid, client_kw)
            rep.message += "; " + _fate(rep)
        return rep
    finally:
        if client is not None:
            rep.tx_bytes, rep.rx_bytes, rep.wire_s, rep.resent = \
                client.tx_bytes, client.rx_bytes, client.wire_s, client.resent
            client.close()
        rep.seconds = time.monotonic() - t0


def _probe(port: str, uid: int, client_kw: dict) -> bytes | None:
    """After a failure: ask (patiently) which config the board runs now."""
    kw = dict(client_kw, retries=max(6, client_kw.get("retries", 4)), uid=uid)
    try:
        with BoardClient(port, **kw) as c:
            info = c.identify()
            return info.config_hash if info.flags & P.FLAG_CONFIG_VALID else None
    except BoardError:
        return None


def _fate(rep: BoardReport) -> str:
    if rep.active_hash is None:
        return "the board did not answer afterwards; its commit is atomic, so it runs either the old or the new config"
    if rep.active_hash == rep.new_hash:
        return "the board runs the new config, but it could not be verified"
    if rep.active_hash == rep.old_hash:
        return "the board kept its old config"
    return f"the board runs config {rep.active_hash.hex()[:8]}, neither the old nor the new one; deploy again"


def discover(candidates: list[str], timeout: float = 0.2, retries: int = 1, baud: int = 1_000_000
             ) -> dict[int, tuple[str, P.Identity]]:
    """Identify whatever answers on each candidate port: uid -> (port, identity). Silent ports are skipped."""
    def probe(port):
        try:
            with BoardClient(port, baud=baud, timeout=timeout, retries=retries) as c:
                return port, c.identify()
        except BoardError:
            return port, None

    found = {}
    with ThreadPoolExecutor(max(1, min(16, len(candidates)))) as pool:
        for port, info in pool.map(probe, sorted(set(candidates))):
            if info is not None:
                found.setdefault(info.uid, (port, info))
    return found


def candidate_ports(globs: list[str] = (), system: bool = True) -> list[str]:
    """Serial ports from `serial.tools.list_ports` plus those matching `globs` (e.g. an emulator's link folder)."""
    ports = []
    if system:
        from serial.tools import list_ports
        ports += [p.device for p in list_ports.comports()]
    for g in globs:
        ports += sorted(glob.glob(g))
    return ports


@dataclass
class Plan:
    """Which port each board of the design is on (matched by uid), and what could not be matched."""

    configs: list[BoardConfig]
    ports: dict[int, str] = field(default_factory=dict)  # board id -> port
    missing: list[Board] = field(default_factory=list)
    strangers: dict[int, str] = field(default_factory=dict)  # uid -> port of boards not in the map


def plan(design: SkinDesign, found: dict[int, tuple[str, P.Identity]]) -> Plan:
    """Match discovered boards to the design's boards by unique id (never by port order)."""
    p = Plan(board_configs(design))
    by_uid = {b.uid: b for b in design.boards}
    for b in design.boards:
        if b.uid in found:
            p.ports[b.id] = found[b.uid][0]
        else:
            p.missing.append(b)
    p.strangers = {uid: port for uid, (port, _) in found.items() if uid not in by_uid}
    return p


def deploy(design: SkinDesign, ports: dict[int, str], dry_run: bool = False, force: bool = False,
           configs: list[BoardConfig] | None = None, on_done=None, verify: str = "readback",
           **client_kw) -> list[BoardReport]:
    """Deploy to the boards named in `ports` (board id -> port), all links in parallel; one report per board."""
    configs = configs or board_configs(design)
    jobs = [(cfg, b) for cfg, b in zip(configs, design.boards) if b.id in ports]

    def one(job):
        rep = deploy_board(job[0], job[1], ports[job[1].id], dry_run, force, verify, **client_kw)
        if on_done:
            on_done(rep)
        return rep

    with ThreadPoolExecutor(max(1, len(jobs))) as pool:
        return list(pool.map(one, jobs))

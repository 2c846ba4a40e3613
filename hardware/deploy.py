"""Deploy a taxel map to its boards: find them, push each board's config, commit, read back, compare hashes.

Every board either ends up running the new config (verified by reading it back) or keeps its old
one; a board that fails is reported with the reason and with what it runs afterwards (its state:
untouched, committed, rolled back, or unknown when it stopped answering).
"""
from __future__ import annotations

import glob
import hashlib
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

from skinsafe.core.skin.model import Board, DesignError, SkinDesign
from skinsafe.hardware import protocol as P
from skinsafe.hardware.board_config import BoardConfig, board_configs, diff
from skinsafe.hardware.client import BoardClient, BoardError, identity_problem

STATES = {  # what a board runs after the command, in words for the report
    "untouched": "no config byte was sent; the board runs what it ran before",
    "committed": "the board runs the new config",
    "rolled back": "a transfer began but was not committed; the board keeps its old config",
    "unknown": "the board did not answer afterwards; its commit is atomic, so it runs the old or the new config",
}


@dataclass
class BoardReport:
    """The outcome for one board; `active_hash` is what the board runs afterwards (None: unknown or none).

    `status`: updated | unchanged | would-update | refused | failed | missing | cancelled;
    `state` (what the board runs): untouched | committed | rolled back | unknown (see STATES).
    """

    board: Board
    port: str | None
    status: str
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
    state: str = "untouched"
    kind: str = ""  # the BoardError kind of a failure (timeout, malformed, ...)

    @property
    def ok(self) -> bool:
        return self.status in ("updated", "unchanged", "would-update")

    def line(self) -> str:
        b = self.board
        head = f"board {b.id} '{b.name}' uid {b.uid:#x}" + (f" on {self.port}" if self.port else "")
        h = lambda x: x.hex()[:8] if x else "none"  # noqa: E731
        out = f"{head}: {self.status} [{self.state}]"
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
    why = identity_problem(info, board)
    if why:
        return why
    if not info.capabilities & P.CAP_READBACK:
        return "the board cannot read its config back; update the board firmware"
    if info.flags & P.FLAG_STREAMING:
        return "the board is streaming; stop `skinsafe stream` (or reset the board) and deploy again"
    return None


def deploy_board(cfg: BoardConfig, board: Board, port: str, dry_run: bool = False, force: bool = False,
                 verify: str = "readback", cancel=None, **client_kw) -> BoardReport:
    """Push one board's config over `port` and verify it; never raises for board or link trouble.

    verify "readback": read the whole config back and hash it here; "hash": the board hashes its flash.
    `cancel` (an Interrupt): stop before the next request, then say what the board runs.
    """
    if verify not in ("readback", "hash"):
        raise ValueError(f"verify={verify!r}: use 'readback' or 'hash'")
    t0 = time.monotonic()
    data, digest = cfg.to_bytes(), cfg.sha256
    rep = BoardReport(board, port, "failed", new_hash=digest)
    client, sent = None, False
    try:
        client = BoardClient(port, cancel=cancel, **client_kw)
        info = client.identify()
        rep.old_hash = info.config_hash if info.flags & P.FLAG_CONFIG_VALID else None
        why = check_compatible(info, cfg, board, port)
        if why:
            rep.status, rep.message, rep.active_hash, rep.kind = "refused", why, rep.old_hash, "incompatible"
            return rep
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
        rep.state = "committed"  # acknowledged: from here on the board runs the new config
        if verify == "hash":
            rep.active_hash = client.flash_hash()
        else:
            rep.active_hash = hashlib.sha256(client.read_config(len(data))).digest()
        if rep.active_hash != digest:
            rep.state = "unknown"
            rep.message = f"the config in the board's flash differs from the one sent ({verify}); deploy again"
            return rep
        rep.status = "updated"
        return rep
    except (BoardError, DesignError) as e:
        rep.kind = getattr(e, "kind", "malformed")
        rep.status = {"cancelled": "cancelled", "incompatible": "refused"}.get(rep.kind, "failed")
        rep.message = str(e)
        if not sent:
            rep.active_hash = rep.old_hash
            rep.message += "; no config was sent, so the board keeps the one it had"
        elif rep.state != "committed":
            answered, rep.active_hash = _probe(port, cfg.uid, client_kw, quick=cancel is not None and cancel.requested)
            rep.state = _state(rep, answered)
            rep.message += "; " + STATES[rep.state]
            if rep.state == "rolled back" and rep.old_hash is None:
                rep.message = rep.message.replace("keeps its old config", "still has no config, as before")
        else:
            rep.message += "; the commit was acknowledged, so the board runs the new config (not verified)"
        return rep
    finally:
        if client is not None:
            rep.tx_bytes, rep.rx_bytes, rep.wire_s, rep.resent = \
                client.tx_bytes, client.rx_bytes, client.wire_s, client.resent
            client.close()
        rep.seconds = time.monotonic() - t0


def _probe(port: str, uid: int, client_kw: dict, quick: bool = False) -> tuple[bool, bytes | None]:
    """After a failure: ask which config the board runs now -> (it answered, active hash or None)."""
    kw = dict(client_kw, retries=1 if quick else max(6, client_kw.get("retries", 4)), uid=uid)
    try:
        with BoardClient(port, **kw) as c:
            info = c.identify()
            return True, info.config_hash if info.flags & P.FLAG_CONFIG_VALID else None
    except BoardError:
        return False, None


def _state(rep: BoardReport, answered: bool) -> str:
    """What a board whose transfer began runs, from the probe after the failure."""
    if not answered:
        return "unknown"
    if rep.active_hash == rep.new_hash:
        return "committed"
    if rep.active_hash == rep.old_hash:  # a fresh board that still has no config included
        return "rolled back"
    return "unknown"


@dataclass
class Discovery:
    """What answered on the candidate ports: boards by uid, ports skipped with the reason, uids seen twice."""

    found: dict[int, tuple[str, P.Identity]] = field(default_factory=dict)
    skipped: dict[str, str] = field(default_factory=dict)  # port -> why no board was found there
    duplicates: dict[int, list[str]] = field(default_factory=dict)  # uid -> ports (refused: deploy to neither)
    skipped_uids: dict[int, str] = field(default_factory=dict)  # uid -> port, for skipped ports whose frames named it
    probed: int = 0


def discover(candidates: list[str], timeout: float = 0.2, retries: int = 1, baud: int = 1_000_000,
             cancel=None) -> Discovery:
    """Identify whatever answers on each candidate port, in parallel; every port ends found or skipped with a reason."""
    def probe(port):
        try:
            with BoardClient(port, baud=baud, timeout=timeout, retries=retries, cancel=cancel) as c:
                return port, c.identify(), None
        except BoardError as e:
            return port, None, e

    out = Discovery()
    ports = sorted(set(candidates))
    out.probed = len(ports)
    seen: dict[int, list[tuple[str, P.Identity]]] = {}
    with ThreadPoolExecutor(max(1, min(16, len(ports)))) as pool:
        for port, info, err in pool.map(probe, ports):
            if info is None:
                out.skipped[port] = f"{err.kind}: {str(err).removeprefix(port + ': ')}"
                if err.uid is not None:
                    out.skipped_uids[err.uid] = port
            else:
                seen.setdefault(info.uid, []).append((port, info))
    for uid, hits in seen.items():
        ports = [port for port, _ in hits] + ([out.skipped_uids[uid]] if uid in out.skipped_uids else [])
        if len(ports) == 1:
            out.found[uid] = hits[0]
            continue
        out.duplicates[uid] = sorted(ports)  # a skipped port whose frames named this uid counts too
        for port, _ in hits:
            out.skipped[port] = (f"duplicate uid: board uid {uid:#x} answers on {len(ports)} ports "
                                 f"({', '.join(out.duplicates[uid])}); give each board its own uid")
    return out


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
    """Which port each board of the design is on (matched by uid), and why the others were not found."""

    configs: list[BoardConfig]
    ports: dict[int, str] = field(default_factory=dict)  # board id -> port
    missing: dict[int, str] = field(default_factory=dict)  # board id -> why it was not found
    strangers: dict[int, str] = field(default_factory=dict)  # uid -> port of boards not in the map


def plan(design: SkinDesign, found: Discovery) -> Plan:
    """Match discovered boards to the design's boards by unique id (never by port order)."""
    p = Plan(board_configs(design))
    by_uid = {b.uid: b for b in design.boards}
    for b in design.boards:
        if b.uid in found.found:
            p.ports[b.id] = found.found[b.uid][0]
        else:
            p.missing[b.id] = _why_missing(b, found)
    p.strangers = {uid: port for uid, (port, _) in found.found.items() if uid not in by_uid}
    return p


def _why_missing(b: Board, d: Discovery) -> str:
    if b.uid in d.duplicates:
        return (f"uid {b.uid:#x} answers on {len(d.duplicates[b.uid])} ports ({', '.join(d.duplicates[b.uid])}); "
                "not deployed to either: give each board its own uid")
    if b.uid in d.skipped_uids:
        port = d.skipped_uids[b.uid]
        return f"answered on {port} ({d.skipped[port]}), so it was skipped"
    if not d.probed:
        return "no serial port to probe; connect the board, or give --port or --glob"
    skipped = [f"{port} ({why})" for port, why in sorted(d.skipped.items()) if not why.startswith("duplicate")]
    if skipped:
        return f"not found; {len(skipped)} of {d.probed} ports gave no board: " + "; ".join(skipped)
    return f"not found; all {d.probed} ports answered with other uids"


def missing_reports(design: SkinDesign, p: Plan) -> list[BoardReport]:
    """A report per board of the map that discovery did not find (nothing was sent to it)."""
    return [BoardReport(b, None, "missing", p.missing[b.id], kind="missing") for b in design.boards if b.id in p.missing]


def deploy(design: SkinDesign, ports: dict[int, str], dry_run: bool = False, force: bool = False,
           configs: list[BoardConfig] | None = None, on_done=None, verify: str = "readback", cancel=None,
           **client_kw) -> list[BoardReport]:
    """Deploy to the boards named in `ports` (board id -> port), each link in its own thread; one report per
    board. Boards are independent: one failing (or raising by a bug) never stops the others."""
    configs = configs or board_configs(design)
    jobs = [(cfg, b) for cfg, b in zip(configs, design.boards) if b.id in ports]

    def one(job):
        cfg, b = job
        try:
            rep = deploy_board(cfg, b, ports[b.id], dry_run, force, verify, cancel, **client_kw)
        except Exception as e:  # a bug must not take the other boards down; report it as this board's failure
            rep = BoardReport(b, ports[b.id], "failed", f"internal error {type(e).__name__}: {e}; please report it",
                              new_hash=cfg.sha256, state="unknown", kind="internal")
        if on_done:
            on_done(rep)
        return rep

    with ThreadPoolExecutor(max(1, len(jobs))) as pool:
        return list(pool.map(one, jobs))

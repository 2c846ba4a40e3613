"""`skinsafe bench serial`: deploy+verify a map over emulated 1 Mbaud links, and stream decoding speed.

deploy_s: measured wall time of deploy + verify (verify "readback": the whole config read back;
"hash": the board hashes its flash) to emulators on ptys that pace their link like a UART at
--baud (8N1); wire_s: the bytes each link carried x 10 bits / baud (the
slowest link; boards deploy in parallel). decode_x_wire: how many times faster than real time
one second of streaming from all channels at --rate is parsed (CRCs checked), decoded to newtons
and put in taxel order (wall-time median; decode_cpu_x_wire the same from this process's CPU
time, which a loaded machine skews less); speedup_vs_loop compares with decoding frame by frame via FSRModel.decode.
"""
from __future__ import annotations

import tempfile

import numpy as np

from skinsafe.core.bench import serial_faults
from skinsafe.core.skin.model import SkinDesign
from skinsafe.core.timing import cpu_median_ms, median_ms
from skinsafe.hardware import protocol as P
from skinsafe.hardware.board_config import board_configs, channel_rows, default_sensor
from skinsafe.hardware.deploy import deploy
from skinsafe.hardware.emulator import EmulatorProcess
from skinsafe.hardware.flat_design import flat_design
from skinsafe.hardware.stream import decode_frames, decode_table


def add_arguments(p) -> None:
    p.add_argument("--taxels", type=int, default=4096)
    p.add_argument("--boards", type=int, nargs="+", default=[1, 4, 16])
    p.add_argument("--baud", type=int, default=1_000_000)
    p.add_argument("--rate", type=int, default=1000, help="stream frames per second per board")
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--verify", nargs="+", choices=["readback", "hash"], default=["readback", "hash"])
    serial_faults.add_arguments(p)


def stream_bytes(design: SkinDesign, seconds_of_frames: int, seed: int = 0) -> list[bytes]:
    """Wire bytes per board for `seconds_of_frames` frames of random counts."""
    rng = np.random.default_rng(seed)
    out = []
    for b in design.boards:
        frames = []
        for k in range(seconds_of_frames):
            counts = rng.integers(0, 4096, b.capacity, dtype=np.uint16).astype("<u2")
            frames.append(P.encode_frame(P.STREAM_DATA, k, b.uid, P.STREAM_HEAD.pack(k * 1000, k, b.capacity, 0)
                                         + counts.tobytes()))
        out.append(b"".join(frames))
    return out


def decode_all(design: SkinDesign, wires: list[bytes], table: np.ndarray, read_size: int = 65536) -> np.ndarray:
    """Parse and decode every board's bytes (read in `read_size` pieces) into the latest (N,) forces."""
    force = np.full(design.n_taxels, np.nan)
    for b, wire in zip(design.boards, wires):
        parser = P.FrameParser(runs=True)
        rows = channel_rows(design, b)
        channels = design.taxels.channel[rows]
        for i in range(0, len(wire), read_size):
            frames = parser.feed(wire[i:i + read_size])
            if frames:
                _, f = decode_frames(frames, b.capacity, channels, table)
                force[rows] = f[-1]
    return force


def decode_loop(design: SkinDesign, wires: list[bytes], decode, n_frames: int) -> np.ndarray:
    """Reference: frame by frame, FSRModel.decode on each frame's mapped channels."""
    force = np.full(design.n_taxels, np.nan)
    for b, wire in zip(design.boards, wires):
        rows = channel_rows(design, b)
        channels = design.taxels.channel[rows]
        for fr in P.FrameParser().feed(wire)[:n_frames]:
            force[rows] = decode(np.frombuffer(fr.payload, "<u2", b.capacity, P.STREAM_HEAD.size)[channels])
    return force


def rows(args) -> list[dict]:
    if args.faults:
        return serial_faults.rows(args)
    fsr = default_sensor()
    table = decode_table(fsr.decode)
    out = []
    for nb in args.boards:
        design = flat_design(args.taxels, nb)
        configs = board_configs(design, fsr.encode)
        pushes = {}
        with tempfile.TemporaryDirectory() as flash, \
                EmulatorProcess([(b.uid, b.capacity) for b in design.boards], flash, "--baud", str(args.baud)) as em:
            ports = {b.id: em.ports[b.uid] for b in design.boards}
            for verify in args.verify:
                reports = []

                def push():
                    reports[:] = deploy(design, ports, force=True, configs=configs, verify=verify, baud=args.baud,
                                        timeout=1.0)
                    bad = [r.line() for r in reports if r.status != "updated"]
                    if bad:
                        raise RuntimeError("deploy failed in the benchmark: " + "; ".join(bad))

                pushes[verify] = (median_ms(push, repeat=args.repeat, warmup=1), list(reports))
        wires = stream_bytes(design, args.rate)
        fast_ms = median_ms(lambda: decode_all(design, wires, table), repeat=args.repeat, warmup=1)
        cpu_ms = cpu_median_ms(lambda: decode_all(design, wires, table), args.repeat)
        n_ref = max(1, args.rate // 20)
        loop_ms = median_ms(lambda: decode_loop(design, wires, fsr.decode, n_ref), repeat=args.repeat, warmup=1)
        check = decode_all(design, [w[:len(w) // args.rate * n_ref] for w in wires], table)
        if not np.array_equal(check, decode_loop(design, wires, fsr.decode, n_ref)):
            raise RuntimeError("the table decode differs from FSRModel.decode")
        for verify, (deploy_ms, reports) in pushes.items():
            out.append({
                "n_taxels": args.taxels, "boards": nb, "baud": args.baud, "verify": verify,
                "deploy_s": deploy_ms / 1e3,
                "wire_s": max(r.wire_s for r in reports),
                "wire_bytes": sum(r.tx_bytes + r.rx_bytes for r in reports),
                "decode_ms_per_s": fast_ms,
                "decode_x_wire": 1e3 / fast_ms,
                "decode_cpu_x_wire": 1e3 / cpu_ms,
                "speedup_vs_loop": loop_ms * args.rate / n_ref / fast_ms,
            })
    return out

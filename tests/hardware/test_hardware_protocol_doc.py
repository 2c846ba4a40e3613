"""hardware/PROTOCOL.md's tables against the code's constants: the document a firmware author reads is the code's truth."""
import re
from pathlib import Path

import numpy as np

from skinsafe.hardware import board_config as C
from skinsafe.hardware import protocol as P
from skinsafe.hardware.emulated_board import BoardSpec, EmulatedBoard

DOC = (Path(P.__file__).parent / "PROTOCOL.md").read_text()


def tables() -> list[list[list[str]]]:
    """Every markdown table of the document: rows of cells, the header row first."""
    out, cur = [], []
    for line in DOC.splitlines() + [""]:
        if line.startswith("|"):
            cells = [c.strip() for c in line.strip().strip("|").split("|")]
            if not all(re.fullmatch(r":?-+:?", c) for c in cells):
                cur.append(cells)
        elif cur:
            out.append(cur)
            cur = []
    return out


def table(*header: str) -> list[list[str]]:
    hits = [t[1:] for t in tables() if tuple(t[0][:len(header)]) == header]
    assert len(hits) >= 1, f"no table with columns {header}"
    return hits[0] if len(hits) == 1 else hits


def _layout(rows) -> list[tuple[int, str]]:
    """(offset, size) rows whose offset and size are numbers; each field starts where the one before ended."""
    out = [(int(o), int(s)) for o, s, *_ in rows if o.isdigit() and s.isdigit()]
    assert all(o + s == o2 for (o, s), (o2, _) in zip(out, out[1:])), out
    return out


def test_status_table_is_the_codes_status_list():
    rows = table("status", "meaning")
    assert {int(code): meaning for code, meaning in rows} == P.STATUS


def test_message_table_types_names_broadcast_and_streaming_rules():
    rows = table("type", "request", "request payload", "answer data (status ok)", "broadcast", "while streaming")
    requests = {int(t, 16): r for t, r, *_ in rows if t != "0x40"}
    assert {t: n.replace(" ", "-") for t, n in requests.items()} == P.COMMANDS
    assert {int(t, 16) for t, *_, b, _ in rows if b == "yes"} == {P.IDENTIFY}
    assert {int(t, 16) for t, *_, s in rows if s == "yes"} == P.WHILE_STREAMING
    assert any(int(t, 16) == P.STREAM_DATA for t, *_ in rows)
    ident = next(r for r in rows if int(r[0], 16) == P.IDENTIFY)
    assert f"({P.IDENTIFY_RESP.size} bytes)" in ident[3] and f"Identify** answer data ({P.IDENTIFY_RESP.size} bytes)" in DOC


def test_limits_table_matches_the_constants():
    rows = table("name", "value", "meaning")
    assert len(rows) >= 10
    for name, value, _ in rows:
        const = getattr(P, name.strip("`"))
        assert float(value) == const, name


def test_frame_and_stream_layouts_match_the_structs():
    frame, stream, config = table("offset", "size", "field")
    fixed = _layout(frame)
    assert [o for o, _ in fixed] == [0, 2, 3, 4, 6, 14, 16]
    assert sum(s for _, s in fixed) == P.HEADER_SIZE and frame[-1][1] == "4" and P.OVERHEAD == P.HEADER_SIZE + 4
    assert sum(s for _, s in _layout(stream)) == P.STREAM_HEAD.size
    assert sum(s for _, s in _layout(config)) == C.HEADER.size and "12m" in config[-1][1]
    assert C.ENTRY.itemsize == 12 and "Entry (12 bytes)" in DOC
    # the config length bound of identify: the header and an entry per channel, as the layout says
    assert (P.CONFIG_HEADER_BYTES, P.CONFIG_ENTRY_BYTES) == (C.HEADER.size, C.ENTRY.itemsize)
    assert f"`{C.HEADER.size} + {C.ENTRY.itemsize} n_channels`" in DOC and P.max_config_bytes(3) == 24 + 36


def test_prose_figures_follow_from_the_code(tmp_path):
    # the achievable stream rate quoted for 256 channels at 1 Mbaud
    assert f"{int(1e6 / (10 * P.stream_frame_bytes(256)))} for 256 channels at 1 Mbaud" in DOC
    # gain rounding as documented: (raw * gain) >> 8, rounded down, saturating
    board = EmulatedBoard(BoardSpec(7, 4, max_chunk=P.MIN_CHUNK), tmp_path / "flash", replay=np.full((1, 4), 3.0))
    try:
        board.gain[:] = [256, 384, 511, 65535]
        raw = np.asarray(board.encode(np.full(4, 3.0)), np.int64)
        counts = np.frombuffer(board.stream_frame()[P.HEADER_SIZE + P.STREAM_HEAD.size:-4], "<u2")
        assert counts.tolist() == np.minimum(raw * [256, 384, 511, 65535] >> 8, 65535).tolist()
        board.sample = 2 ** 16 + 5  # a frame's sequence number is the low 16 bits of its sample counter
        (frame,) = P.FrameParser().feed(board.stream_frame())
        assert frame.seq == 5 and P.STREAM_HEAD.unpack_from(frame.payload)[1] == 2 ** 16 + 5
    finally:
        board.close()
    assert "`min(65535, (raw * gain) >> 8)`" in DOC
    # the replay bound's slack on the board's clock
    from skinsafe.hardware.stream import CLOCK_SLACK
    assert f"with {round((CLOCK_SLACK[0] - 1) * 100)}% and {round(CLOCK_SLACK[1] * 1000)} ms of slack" in DOC
    # the two CRC check values
    import zlib
    assert f"`0x{P.crc16(b'123456789'):04X}`" in DOC and f"`0x{zlib.crc32(b'123456789'):08X}`" in DOC

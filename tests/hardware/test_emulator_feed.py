"""An emulated board fed by a simulation's shared-memory feed: a feed whose writer stopped in the middle of a
write gives the board no sample, and the board then sends no frame (the host names a lasting gap silent); it is
never fed the last press again, and its thread does not die."""
import numpy as np

from skinsafe.core.skin.force_feed import ForceFeed
from skinsafe.hardware import protocol as P
from skinsafe.hardware.emulated_board import BoardSpec, EmulatedBoard
from skinsafe.hardware.emulator import board_feed
from skinsafe.hardware.flat_design import flat_design


def test_a_feed_stuck_mid_write_gives_no_frame_then_frames_resume(tmp_path):
    design = flat_design(8, 2)
    board = design.boards[1]
    feed = ForceFeed.create(None, design.n_taxels)
    try:
        forces = np.arange(design.n_taxels, dtype=float)
        feed.write(forces, 0.1)
        read = board_feed(feed, board, design, board.capacity)
        rows = np.flatnonzero(design.taxels.board == board.id)
        got = read()
        assert got[design.taxels.channel[rows]].tolist() == forces[rows].tolist()
        em = EmulatedBoard(BoardSpec(board.uid, board.capacity), tmp_path / "flash", feed=read)
        try:
            feed._seq[0] += np.uint64(1)  # the writer stops half-way through a write
            assert read() is None
            sample = em.sample
            assert em.stream_frame() is None and em.sample == sample  # no frame, no sample counted
            feed._seq[0] += np.uint64(1)  # a write completes
            (frame,) = P.FrameParser().feed(em.stream_frame())
            assert frame.type == P.STREAM_DATA and em.sample == sample + 1
        finally:
            em.close()
    finally:
        feed.close()

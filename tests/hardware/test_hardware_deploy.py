"""Deploy over real ptys to emulated boards in a separate process: verify, refuse, survive faults."""
import hashlib

import numpy as np
import pytest

from skinsafe.core.sim.sensor_model import FSRModel
from skinsafe.core.skin.model import DesignError
from skinsafe.hardware import protocol as P
from skinsafe.hardware.board_config import BoardConfig, board_config, board_configs, diff
from skinsafe.hardware.deploy import candidate_ports, deploy, deploy_board, discover, plan
from skinsafe.hardware.emulator import EmulatorProcess, flash_path
from skinsafe.hardware.flat_design import flat_design


def _sha(path):
    return hashlib.sha256(path.read_bytes()).digest()


def test_board_config_bytes_roundtrip_and_thresholds():
    d = flat_design(40, 2, threshold=4.0)
    d.taxels.thresholds["force"][3] = 9.0
    d.taxels.enabled[5] = False
    cfg = board_configs(d)[0]
    data = cfg.to_bytes()
    assert len(data) == 24 + 12 * 20
    back = BoardConfig.from_bytes(data)
    assert back.sha256 == cfg.sha256 == hashlib.sha256(data).digest()
    enc = FSRModel().encode(np.array([4.0, 9.0]))
    assert back.entries["threshold"][3] == enc[1] and back.entries["threshold"][0] == enc[0]
    assert back.entries["flags"][5] == 0 and back.entries["flags"][4] == 1
    assert (back.entries["taxel_id"] == np.arange(20)).all() and (back.entries["gain"] == 256).all()
    d2 = flat_design(40, 2, threshold=4.0)
    d2.taxels.thresholds["force"][0] = 6.0
    assert diff(back, board_configs(d2)[0]) == {"added": 0, "removed": 0, "changed": 3}  # channels 0, 3, 5
    with pytest.raises(DesignError, match="magic"):
        BoardConfig.from_bytes(b"XXXX" + data[4:])
    with pytest.raises(DesignError, match="expected 264"):
        BoardConfig.from_bytes(data[:-1])
    d.taxels.ids[0] = 2 ** 33
    with pytest.raises(DesignError, match="32-bit"):
        board_config(d, d.boards[0])


def test_deploy_and_verify_one_board(tmp_path):
    d = flat_design(200, 1)
    with EmulatorProcess([(b.uid, b.capacity) for b in d.boards], tmp_path) as em:
        ports = {0: em.ports[d.boards[0].uid]}
        (rep,) = deploy(d, ports)
        cfg = board_configs(d)[0]
        assert rep.status == "updated" and rep.ok and rep.old_hash is None
        assert rep.active_hash == cfg.sha256 == _sha(flash_path(tmp_path, cfg.uid))
        # bytes on the wire: the config once each way plus one frame per chunk/request
        assert rep.tx_bytes > len(cfg.to_bytes()) and rep.rx_bytes > len(cfg.to_bytes())
        (again,) = deploy(d, ports)
        assert again.status == "unchanged" and again.tx_bytes == P.OVERHEAD  # only the identify was sent
        (hashed,) = deploy(d, ports, force=True, verify="hash")  # the board hashes its flash: no read back
        assert hashed.status == "updated" and hashed.active_hash == cfg.sha256
        assert hashed.rx_bytes < len(cfg.to_bytes()) < hashed.tx_bytes
        d.taxels.thresholds["force"][:7] = 8.0
        (dry,) = deploy(d, ports, dry_run=True)
        assert dry.status == "would-update" and dry.changes == {"added": 0, "removed": 0, "changed": 7}
        assert _sha(flash_path(tmp_path, cfg.uid)) == cfg.sha256  # a dry run changes nothing


def test_deploy_four_boards_matched_by_uid_not_port_order(tmp_path):
    d = flat_design(1024, 4)
    links = tmp_path / "links"
    with EmulatorProcess([(b.uid, b.capacity) for b in reversed(d.boards)], tmp_path, "--link-dir", str(links)):
        found = discover(candidate_ports([str(links / "board-*")], system=False))
        assert sorted(found.found) == sorted(b.uid for b in d.boards) and not found.skipped
        p = plan(d, found)
        assert not p.missing and not p.strangers
        reports = deploy(d, p.ports)
        assert [r.status for r in reports] == ["updated"] * 4
        for r, cfg in zip(reports, board_configs(d)):
            assert r.port.endswith(f"board-{cfg.uid:016x}")
            assert _sha(flash_path(tmp_path, cfg.uid)) == cfg.sha256 == r.active_hash
        assert len({r.active_hash for r in reports}) == 4


def test_wrong_board_or_channel_count_refused_before_anything_is_sent(tmp_path):
    d = flat_design(256, 2)  # boards of 128 channels, uids ...0 and ...1
    other = flat_design(256, 1, uid_base=d.boards[0].uid)  # same uid as board 0, but 256 channels
    with EmulatorProcess([(d.boards[0].uid, 128)], tmp_path) as em:
        port = em.ports[d.boards[0].uid]
        cfgs = board_configs(d)
        wrong_uid = deploy_board(cfgs[1], d.boards[1], port)
        assert wrong_uid.status == "refused" and "uid 0x5c1a0000" in wrong_uid.message
        wrong_n = deploy_board(board_configs(other)[0], other.boards[0], port)
        assert wrong_n.status == "refused" and "128 channels" in wrong_n.message and "capacity 256" in wrong_n.message
        for rep in (wrong_uid, wrong_n):
            assert rep.tx_bytes == P.OVERHEAD  # the identify request and nothing else
            assert not rep.ok
        assert not flash_path(tmp_path, d.boards[0].uid).exists()


OLD_THRESHOLD, NEW_THRESHOLD = 3.0, 6.0
FAULTS = {  # name: (emulator options, client options, outcome: "new", "old" or "either")
    "dropped bytes": (["--drop", "0.0005", "--seed", "3"], {"timeout": 0.1, "retries": 6}, "new"),
    "flipped bits": (["--flip", "0.0005", "--seed", "4"], {}, "new"),
    "short delays": (["--delay", "0.03"], {}, "new"),
    "delays past the timeout": (["--delay", "0.3", "--delay-p", "0.3", "--seed", "6"],
                                {"timeout": 0.1, "retries": 2}, "either"),
    "reset mid-transfer": (["--reset-at-chunk", "2", "--max-chunk", "256"], {}, "new"),
    "reset on every transfer": (["--reset-at-chunk", "2", "--resets", "-1", "--max-chunk", "256"], {}, "old"),
    "heavy byte loss": (["--drop", "0.001", "--seed", "5"], {"timeout": 0.1, "retries": 2}, "either"),
    "wrong firmware version": (["--firmware", "2.1.0"], {}, "old"),
    "wrong protocol version": (["--protocol", "2"], {}, "old"),
}


@pytest.mark.parametrize("fault", list(FAULTS))
def test_every_fault_leaves_old_or_new_config_and_is_reported(tmp_path, fault):
    extra, client_kw, outcome = FAULTS[fault]
    old, new = flat_design(600, 1, OLD_THRESHOLD), flat_design(600, 1, NEW_THRESHOLD)
    old_cfg, new_cfg = board_configs(old)[0], board_configs(new)[0]
    flash = flash_path(tmp_path, old_cfg.uid)
    flash.write_bytes(old_cfg.to_bytes())  # the board runs the old map
    with EmulatorProcess([(old_cfg.uid, old_cfg.capacity)], tmp_path, *extra) as em:
        rep = deploy_board(new_cfg, new.boards[0], em.ports[old_cfg.uid], **client_kw)
    running = _sha(flash)
    assert running in (old_cfg.sha256, new_cfg.sha256)
    if outcome != "either":
        assert running == (new_cfg.sha256 if outcome == "new" else old_cfg.sha256), rep.line()
    if rep.ok:
        assert rep.status == "updated" and running == new_cfg.sha256 == rep.active_hash
        assert rep.state == "committed"
    else:
        assert rep.status in ("failed", "refused") and rep.message and rep.kind
        # the reported state is what the flash holds: untouched/rolled back -> old, committed -> new
        want = {"untouched": old_cfg.sha256, "rolled back": old_cfg.sha256, "committed": new_cfg.sha256}
        if rep.state == "unknown":
            assert "old or the new config" in rep.message
        else:
            assert running == want[rep.state], rep.line()
            assert rep.state in rep.line()
    if fault.startswith("wrong firmware"):
        assert rep.status == "refused" and "firmware 2.1.0" in rep.message and rep.tx_bytes == P.OVERHEAD
    if fault.startswith("wrong protocol"):
        assert "protocol version 2" in rep.message
    if fault in ("dropped bytes", "flipped bits", "reset mid-transfer"):
        assert rep.resent > 0  # the fault really hit the transfer and was retried


def test_board_survives_malformed_requests(tmp_path):
    from skinsafe.hardware.client import BoardClient, BoardError
    rng = np.random.default_rng(7)
    with EmulatorProcess([(0x5C1A0000, 64)], tmp_path) as em, BoardClient(em.ports[0x5C1A0000], retries=0) as c:
        with pytest.raises(BoardError, match="config-begin failed after 1 tries"):
            c.request(P.CONFIG_BEGIN, bytes(36))  # broadcast: only identify may be, the board ignores it
        c.identify()  # from now on the client addresses the board's uid
        for cmd in list(P.COMMANDS) + [0x33]:
            if cmd == P.RESET:
                continue
            for n in (0, 3, 37):
                try:
                    c.request(cmd, rng.integers(0, 256, n, dtype=np.uint8).tobytes())
                except BoardError as e:
                    assert e.status in P.STATUS and e.status != P.OK  # refused with a reason, never silent
        with pytest.raises(BoardError, match="refused config-begin: malformed request"):
            c.request(P.CONFIG_BEGIN, b"\x01")
        with pytest.raises(BoardError, match="refused 0x33|unknown command"):
            c.request(0x33)
        assert c.identify().uid == 0x5C1A0000 and not flash_path(tmp_path, 0x5C1A0000).exists()


def test_each_emulated_board_draws_faults_from_its_own_seed(tmp_path):
    from skinsafe.hardware.emulated_board import BoardSpec, EmulatedBoard, Faults
    data = bytes(4000)

    def damage(uid, seed):
        b = EmulatedBoard(BoardSpec(uid, 8, faults=Faults(flip=0.01, seed=seed)), tmp_path / f"{uid}-{seed}")
        try:
            return b._wire(data)
        finally:
            b.close()

    one, other, again, next_run = damage(1, 0), damage(2, 0), damage(1, 0), damage(1, 1)
    assert one == again  # one run seed reproduces each board's faults ...
    assert one != other and one != next_run  # ... and boards (and runs) do not share them
    assert 10 < sum(x != 0 for x in one) < 80  # about 40 flipped bytes

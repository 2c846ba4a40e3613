"""Stable taxel ids (module id << 16 | index in the module): independent of the modules' order and of
edits to other modules; a design with them validates, saves and reads back, and its boards' configs carry
them; the map's hash is the hash of the file `save` writes."""
import hashlib

import numpy as np
import pytest

from skinsafe.core.skin import taxel_map
from skinsafe.core.skin.ids import SHIFT, stable_ids, with_stable_ids
from skinsafe.core.skin.model import DesignError
from skinsafe.hardware.board_config import board_configs
from skinsafe.hardware.flat_design import flat_design


def test_ids_are_module_and_index_whatever_the_order():
    module = np.array([5, 5, 0, 5, 0, 9], np.int32)
    assert stable_ids(module).tolist() == [5 << 16, (5 << 16) + 1, 0, (5 << 16) + 2, 1, 9 << 16]
    # removing module 0's taxels or re-ordering the modules leaves module 5's and 9's ids as they were
    assert stable_ids(module[[0, 1, 3, 5]]).tolist() == [5 << 16, (5 << 16) + 1, (5 << 16) + 2, 9 << 16]
    assert stable_ids(np.array([9, 5, 5, 5])).tolist() == [9 << 16, 5 << 16, (5 << 16) + 1, (5 << 16) + 2]
    assert stable_ids(np.zeros(0, np.int32)).shape == (0,)
    with pytest.raises(DesignError, match="module id 65536 is outside 0..65535"):
        stable_ids(np.array([1 << SHIFT]))


def test_a_design_with_stable_ids_saves_reads_back_and_reaches_the_boards(tmp_path):
    d = with_stable_ids(flat_design(300, 3))
    assert d.taxels.ids[:2].tolist() == [0, 1] and d.taxels.ids[100] == 1 << 16 and d.taxels.ids[-1] == (2 << 16) + 99
    back = taxel_map.load(taxel_map.save(d, tmp_path / "skin.json"))
    assert np.array_equal(back.taxels.ids, d.taxels.ids)
    ids = np.concatenate([c.entries["taxel_id"] for c in board_configs(d)])
    assert sorted(ids.tolist()) == sorted(d.taxels.ids.tolist())
    path = tmp_path / "skin.json"
    assert taxel_map.sha256(d) == hashlib.sha256(path.read_bytes()).hexdigest()
    assert taxel_map.sha256(back) == taxel_map.sha256(d)

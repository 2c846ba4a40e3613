"""The taxel map file: exact round trip, validation naming file/item/field, atomic saves."""
import json
from dataclasses import replace

import numpy as np
import pytest

from skinsafe.core.design.sample import make_sample_design
from skinsafe.core.robot.models import build_ur5
from skinsafe.core.skin import taxel_map
from skinsafe.core.skin.model import DesignError, frames_from_normals


@pytest.fixture(scope="module")
def design():
    return make_sample_design("ur5")


@pytest.fixture
def saved(design, tmp_path):
    path = tmp_path / "skin.json"
    taxel_map.save(design, path)
    return path, json.loads(path.read_text())


def _write(tmp_path, raw):
    p = tmp_path / "bad.json"
    p.write_text(json.dumps(raw))
    return p


def test_round_trip_is_exact(design, saved):
    path, raw = saved
    assert raw["schema_version"] == taxel_map.SCHEMA_VERSION
    back = taxel_map.load(path, build_ur5().body_names)
    for name in ("ids", "body", "positions", "frames", "module", "board", "channel", "area", "enabled"):
        a, b = getattr(design.taxels, name), getattr(back.taxels, name)
        assert a.dtype == b.dtype and np.array_equal(a, b), name
    assert np.array_equal(design.taxels.thresholds["force"], back.taxels.thresholds["force"])
    assert back.modules == design.modules and back.boards == design.boards and back.robot == design.robot
    assert back.bodies == design.bodies
    # saving the loaded design gives byte-identical files
    path2 = path.with_name("again.json")
    taxel_map.save(back, path2)
    assert path2.read_bytes() == path.read_bytes()


@pytest.mark.parametrize("mutate,expect", [
    (lambda r: r.update(schema_version=99), "schema_version"),
    (lambda r: r["taxels"]["positions"][5].__setitem__(0, float("nan")), "taxel 5: field 'positions'"),
    (lambda r: r["taxels"]["ids"].__setitem__(7, 3), "taxel 3: field 'id'"),
    (lambda r: r["taxels"]["channel"].__setitem__(10, 5000), "taxel 10: field 'channel'"),
    (lambda r: r["taxels"]["channel"].__setitem__(1, 0), "field 'channel' 0 is used by more than one"),
    (lambda r: r["taxels"]["frames"][4].__setitem__(0, 2.0), "taxel 4: field 'frame'"),
    (lambda r: r["taxels"]["frames"].__setitem__(2, [-v for v in r["taxels"]["frames"][2]]), "taxel 2: field 'frame' is left-handed"),
    (lambda r: r["taxels"]["body"].__setitem__(0, 42), "taxel 0: field 'body'"),
    (lambda r: r["taxels"]["area"].__setitem__(3, 0.0), "taxel 3: field 'area'"),
    (lambda r: r["taxels"]["positions"].pop(), "field 'positions' has shape"),
    (lambda r: r["modules"][0].update(board=77), "module 0 'upper_arm_link_m0': field 'board'"),
    (lambda r: r["modules"][0].update(pitch="wide"), "field 'pitch'"),
    (lambda r: r["taxels"]["thresholds"].pop("force"), "thresholds.force"),
    (lambda r: r["taxels"]["thresholds"].update(smell=[1.0]), "thresholds.smell"),
    (lambda r: r["taxels"]["enabled"].__setitem__(0, 1), "field 'enabled'"),
    (lambda r: r.pop("boards"), "field 'boards' is missing"),
    (lambda r: r.update(retired_modules=[0]), "module 0 'upper_arm_link_m0': field 'id' is retired"),
    (lambda r: r.update(retired_modules=[2.5]), "retired_modules: field 'id' 2.5 is not"),
    (lambda r: r.update(retired_modules=7), "field 'retired_modules' must be a list"),
])
def test_invalid_maps_name_file_item_and_field(saved, tmp_path, mutate, expect):
    _, raw = saved
    mutate(raw)
    bad = _write(tmp_path, raw)
    with pytest.raises(DesignError) as e:
        taxel_map.load(bad)
    assert str(bad) in str(e.value) and expect in str(e.value)


def test_retired_module_ids_are_kept_in_the_map(design, saved, tmp_path):
    """A design's deleted module ids are written and read back, so no later module takes one; a map without any
    has no such field (its bytes as before)."""
    path, raw = saved
    assert "retired_modules" not in raw
    spent = replace(design, retired_modules=(90, 91))
    again = taxel_map.save(spent, tmp_path / "spent.json")
    assert json.loads(again.read_text())["retired_modules"] == [90, 91]
    assert taxel_map.load(again).retired_modules == (90, 91)


def test_unknown_body_in_robot_is_refused(saved, tmp_path):
    _, raw = saved
    raw["bodies"][1] = "tentacle_link"
    with pytest.raises(DesignError, match="body 'tentacle_link'.*does not exist in the robot"):
        taxel_map.load(_write(tmp_path, raw), build_ur5().body_names)


def test_not_json_and_missing_file(tmp_path):
    p = tmp_path / "x.json"
    p.write_text("{not json")
    with pytest.raises(DesignError, match="not valid JSON"):
        taxel_map.load(p)
    with pytest.raises(DesignError, match="not found"):
        taxel_map.load(tmp_path / "nope.json")


def test_failed_save_leaves_old_file_and_no_temp(design, saved):
    path, _ = saved
    before = path.read_bytes()
    bad = design.with_taxels(design.taxels.subset(np.arange(design.n_taxels)))
    bad.taxels.positions[0, 0] = np.inf
    with pytest.raises(DesignError, match="positions"):
        taxel_map.save(bad, path)
    assert path.read_bytes() == before
    assert [p.name for p in path.parent.iterdir()] == [path.name]


def test_frames_from_normals_right_handed_even_for_parallel_hint():
    rng = np.random.default_rng(0)
    n = rng.normal(size=(500, 3))
    n[:10] = [1.0, 0, 0]  # hint parallel to the normal
    F = frames_from_normals(n, np.array([1.0, 0, 0]))
    assert np.allclose(np.einsum("nji,njk->nik", F, F), np.eye(3), atol=1e-12)
    assert np.allclose(np.linalg.det(F), 1)
    assert np.allclose(F[:, :, 2], n / np.linalg.norm(n, axis=1, keepdims=True))

"""A skin that can be built, on three robots' own descriptions (the UR5e, the Kinova Gen3 and the
xArm7): every placement either stays within its FPC's in-plane strain with no two pads overlapping,
or is refused naming the module; every module's pads are where an independent wrap of its flat
pattern puts them; `check` refuses a stretched module, naming it."""
import json
import warnings
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from skinsafe.core.app.cli import main
from skinsafe.core.design.audit import module_strains, strain_problems
from skinsafe.core.design.placement import PlacementError, place_module, template_grid
from skinsafe.core.design.roundtrip import roundtrip
from skinsafe.core.design.strain import module_strain
from skinsafe.core.design.surface import cached_surfaces
from skinsafe.core.skin.ids import IdRuleWarning, stable_ids
from skinsafe.core.skin.model import Module, frames_from_normals
from skinsafe.core.skin.taxel_map import load

pytestmark = pytest.mark.xdist_group("public-robots")  # the session's public skins, built once on one worker

ROBOTS = ["ur5e", "gen3", "xarm7"]


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(robot=st.sampled_from(ROBOTS), link=st.integers(0, 1), seed=st.integers(0, 2 ** 31 - 1),
       size=st.sampled_from([(2, 2), (3, 3), (4, 6), (8, 8)]))
def test_a_placement_is_buildable_or_refused_by_name(public_skin, robot, link, seed, size):
    model = public_skin(robot)[0].model
    body = public_skin.links[robot][link]
    surface = cached_surfaces(model, [body])[body]
    rng = np.random.default_rng(seed)
    anchor = surface.random_points(1, seed=seed)[0]
    m = Module(7, "probe", body, rows=size[0], cols=size[1], pitch=0.01, taxel_diameter=0.006, margin=0.001,
               min_bend_radius=0.005)
    try:
        p = place_module(surface, m, anchor, rng.normal(size=3))
    except PlacementError as e:
        assert str(e).startswith("module 7 'probe':") and e.kind in ("off_surface", "bend_radius", "strain")
        return
    uv, row, col = template_grid(m)
    strain = module_strain(uv, row, col, p.positions, p.frames[:, :, 2])
    assert strain.max <= m.max_strain and strain.max == pytest.approx(p.strain)
    gaps = np.linalg.norm(p.positions[:, None] - p.positions[None], axis=2) + np.eye(len(p)) * 1.0
    assert gaps.min() >= m.taxel_diameter  # no two pads of the circuit overlap


@pytest.mark.parametrize("robot", ROBOTS)
def test_every_pad_is_where_the_wrapped_pattern_puts_it(public_skin, robot):
    bot, design, _ = public_skin(robot)
    trips = roundtrip(design, bot.model)
    assert len(trips) == len(design.modules)  # every module checked
    worst = max(float(r.error.max()) for r in trips)
    assert worst <= 1e-3, worst
    strains = module_strains(design)
    assert max(v[0] for v in strains.values()) <= 0.01


def _stretched(design, surface, module_id: int, factor: float):
    """The design with one module's pads spread by `factor` about their centre (back on the surface)."""
    t = design.taxels.subset(np.arange(design.n_taxels))
    on = np.flatnonzero(t.module == module_id)
    centre = t.positions[on].mean(axis=0)
    q, n = surface.closest(centre + factor * (t.positions[on] - centre))[:2]
    t.positions[on] = q
    t.frames[on] = frames_from_normals(n, t.frames[on, :, 0])
    return design.with_taxels(t)


def test_check_refuses_a_stretched_module_naming_it_worst_first(public_skin, capsys):
    from skinsafe.core.skin.taxel_map import save

    bot, design, path = public_skin("ur5e")
    body = design.bodies[0]
    surface = cached_surfaces(bot.model, [body])[body]
    first, second = [m.id for m in design.modules if m.body == body][:2]
    bad = _stretched(_stretched(design, surface, first, 1.03), surface, second, 1.08)
    lines = strain_problems(bad)
    assert len(lines) == 2 and lines[0].startswith(f"module {second} ") and lines[1].startswith(f"module {first} ")
    worst = float(lines[0].split("in-plane strain ")[1].split("%")[0])
    assert 7.0 < worst < 9.0  # the 8% spread, measured
    stretched = save(bad, path.parent / "stretched.json")  # beside the map: its robot reference holds
    assert main(["check", str(stretched)]) == 1
    err = capsys.readouterr().err
    assert f"refused: module {second} " in err and "over the FPC's 1.0%" in err
    assert err.index(f"module {second} ") < err.index(f"module {first} ")


def test_a_map_with_the_other_id_rule_is_converted_once_on_load(public_skin):
    _, design, path = public_skin("gen3")
    raw = json.loads(path.read_text())
    assert raw["taxels"]["ids"] == stable_ids(np.array(raw["taxels"]["module"])).tolist()  # written under the rule
    raw["taxels"]["ids"] = list(range(len(raw["taxels"]["ids"])))  # as `design` wrote maps before the one rule
    old = path.parent / "old-rule.json"
    old.write_text(json.dumps(raw))
    with pytest.warns(IdRuleWarning, match=r"old-rule\.json: \d+ of \d+ taxel ids .* need a new `skinsafe deploy`"):
        converted = load(old)
    np.testing.assert_array_equal(converted.taxels.ids, design.taxels.ids)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert load(path).taxels.ids.tolist() == design.taxels.ids.tolist()  # the rule's own maps: no message


def test_a_module_over_its_own_tolerance_is_refused_by_its_field(public_skin):
    bot, design, _ = public_skin("xarm7")
    strict = replace(design, modules=[replace(m, max_strain=1e-6) for m in design.modules])
    lines = strain_problems(strict, show=3)
    assert len(lines) == 4 and lines[-1].startswith("... and ") and f"of {len(design.modules)})" in lines[-1]

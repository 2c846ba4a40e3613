"""`skinsafe export MAP DIR --fab`: each FPC module's flat pattern as KiCad, DXF, SVG and PDF files, a BOM and
fab.json, read back with parsers of their own (a small S-expression reader for KiCad, ezdxf for the DXF) and checked
in numbers against the template (KiCad: mm, y down, module centre at `KICAD_ORIGIN_MM`; DXF: mm, y up)."""
import csv
import json
import re
import xml.etree.ElementTree as ET
import zlib
from dataclasses import replace

import ezdxf
import numpy as np
import pytest

from skinsafe.core.app.cli import main
from skinsafe.core.design.placement import PlacedModule, build_design, template_grid
from skinsafe.core.skin import taxel_map
from skinsafe.core.skin.model import Module, RobotRef, frames_from_normals
from skinsafe.exporters import fab as fab_module
from skinsafe.exporters.fab import KICAD_ORIGIN_MM, PIN_PITCH_MM, TAIL_MM, rect_union

RADIUS = 0.03  # m: module 0 wraps a cylinder around its rows, so neighbouring columns turn by pitch / RADIUS
L_SHAPE = np.array([(-20, -20), (20, -20), (20, 0), (0, 0), (0, 20), (-20, 20)]) / 1e3  # module 2's outline


def _placed(m: Module, radius=None, z0=0.0, outline=None) -> PlacedModule:
    """The module's template flat at height z0, or wrapped on a cylinder of axis y (exact, no surface needed)."""
    uv, row, col = template_grid(m, outline)
    a = uv[:, 0] / radius if radius else 0 * uv[:, 0]
    r = radius or 0.0
    pos = np.stack([r * np.sin(a) if radius else uv[:, 0], uv[:, 1], r * np.cos(a) + z0], 1)
    nrm = np.stack([np.sin(a), 0 * a, np.cos(a)], 1)
    return PlacedModule(m, pos, frames_from_normals(nrm, np.stack([np.cos(a), 0 * a, -np.sin(a)], 1)), row, col, np.inf)


@pytest.fixture(scope="module")
def design():
    """Three modules on three boards of 16 channels: a 3x4 rect wrapped on a cylinder, a flat 1x5 strip, a 4x4
    'curve' cut to an L (12 taxels); channels shuffled on each board so a net can only be right by its taxel."""
    m0 = Module(0, "wrap", "link1", rows=3, cols=4, pitch=0.01, taxel_diameter=0.006, margin=0.002)
    m1 = Module(1, "strip", "link1", template="strip", rows=1, cols=5, pitch=0.008, taxel_diameter=0.005, margin=0.001)
    m2 = Module(2, "ell", "link2", template="curve", rows=4, cols=4, pitch=0.01, taxel_diameter=0.004, margin=0.001,
                placement={"outline": L_SHAPE.tolist()})
    d = build_design(RobotRef(), [_placed(m0, RADIUS), _placed(m1, z0=0.2), _placed(m2, outline=L_SHAPE)], capacity=16)
    t = d.taxels
    rng = np.random.default_rng(3)
    channel = t.channel.copy()
    for b in np.unique(t.board):
        on = np.flatnonzero(t.board == b)
        channel[on] = rng.permutation(16)[:len(on)]
    return d.with_taxels(replace(t, channel=channel))


@pytest.fixture(scope="module")
def exported(design, tmp_path_factory):
    root = tmp_path_factory.mktemp("fab")
    path = taxel_map.save(design, root / "skin.json")
    assert main(["export", str(path), str(root / "out"), "--fab"]) == 0
    fab = root / "out" / "fab"
    return fab, json.loads((fab / "fab.json").read_text())


def _taxels(design, m: Module):
    """(ids, uv in m, net names) of a module in template order."""
    on = design.taxels.module == m.id
    uv = template_grid(m, m.placement.get("outline"))[0]
    nets = [f"B{b}_CH{c:03d}" for b, c in zip(design.taxels.board[on], design.taxels.channel[on])]
    return design.taxels.ids[on], uv, nets


def sexpr(text: str):
    """A KiCad file as nested lists of strings (quoted strings unquoted)."""
    stack: list = [[]]
    for tok in re.findall(r'\(|\)|"(?:\\.|[^"\\])*"|[^\s()"]+', text):
        if tok == "(":
            stack.append([])
        elif tok == ")":
            done = stack.pop()
            stack[-1].append(done)
        else:
            stack[-1].append(tok[1:-1].replace('\\"', '"') if tok.startswith('"') else tok)
    return stack[0][0]


def kids(node, name):
    return [c for c in node if isinstance(c, list) and c and c[0] == name]


def one(node, name):
    (c,) = kids(node, name)
    return c


def _xy(node) -> np.ndarray:
    return np.array([float(node[1]), float(node[2])])


def _board(fab, entry):
    return sexpr((fab / entry["files"]["kicad_pcb"]).read_text())


def test_kicad_pads_sit_on_the_flat_pattern_with_their_taxels_nets(design, exported):
    fab, index = exported
    ox, oy = KICAD_ORIGIN_MM
    for m, entry in zip(design.modules, index["modules"]):
        board = _board(fab, entry)
        assert board[0] == "kicad_pcb"
        declared = {n[2]: n[1] for n in kids(board, "net")}
        ids, uv, nets = _taxels(design, m)
        pads, pins = {}, {}
        for fp in kids(board, "footprint"):
            at = _xy(one(fp, "at"))
            ref = next(t[2] for t in kids(fp, "fp_text") if t[1] == "reference")
            for pad in kids(fp, "pad"):
                net = one(pad, "net")
                assert declared[net[2]] == net[1]  # the pad's net number is the board's for that name
                rec = (at + _xy(one(pad, "at")), pad, net[2])
                if ref == "J1":
                    pins[int(pad[1])] = rec
                else:
                    assert ref not in pads
                    pads[ref] = rec
        assert sorted(pads) == sorted(f"T{i}" for i in ids)  # exactly one pad per taxel
        assert len(pins) == len(ids) + 1 and sorted(pins) == list(range(1, len(ids) + 2))
        for k, (tid, (u, v), net) in enumerate(zip(ids, uv, nets)):
            xy, pad, pad_net = pads[f"T{tid}"]
            # KiCad's y points down: x = origin + 1000 u, y = origin - 1000 v (mm)
            assert np.abs(xy - [ox + u * 1e3, oy - v * 1e3]).max() < 2e-6, (m.name, tid)
            assert pad[2:4] == ["smd", "circle"] and np.allclose(_xy(one(pad, "size")), m.taxel_diameter * 1e3)
            assert pad_net == net  # the taxel map's board and channel for this taxel id
            assert pins[k + 1][2] == net  # pin k + 1 carries the k-th taxel
        assert pins[len(ids) + 1][2] == f"B{m.board}_COM"
        assert len(declared) == len(ids) + 2  # one net per taxel, the return, KiCad's unnamed net 0
        pitch = np.diff(sorted(p[0][0] for p in pins.values()))
        assert np.allclose(pitch, PIN_PITCH_MM)


def _loops(board) -> list[np.ndarray]:
    """Edge.Cuts segments chained into loops; fails unless every loop closes."""
    segs = [(tuple(one(g, "start")[1:3]), tuple(one(g, "end")[1:3]))
            for g in kids(board, "gr_line") if one(g, "layer")[1] == "Edge.Cuts"]
    nxt = dict(segs)
    assert len(nxt) == len(segs)
    loops = []
    while nxt:
        start = next(iter(nxt))
        loop, p = [], start
        while True:
            loop.append(p)
            p = nxt.pop(p)  # KeyError: a segment ends where none starts (an open outline)
            if p == start:
                break
        loops.append(np.array(loop, dtype=float))
    return loops


def test_edge_cuts_close_around_cells_margin_and_tail(design, exported):
    fab, index = exported
    corners, sizes = [], []
    for m, entry in zip(design.modules, index["modules"]):
        (loop,) = _loops(_board(fab, entry))
        corners.append(len(loop))
        sizes.append(np.ptp(loop, axis=0))
        assert np.allclose(sizes[-1], entry["outline_mm"])
    # FPC edge max(pitch / 2, diameter / 2 + margin) from the outer pad centres, the tail TAIL_MM below that
    assert np.allclose(sizes[0], [30 + 10, 20 + 10 + TAIL_MM])
    assert np.allclose(sizes[1], [32 + 8, 8 + TAIL_MM])
    assert np.allclose(sizes[2], [40, 40 + TAIL_MM])
    assert corners == [8, 8, 10]  # rectangle + tail; the L + tail


def test_dxf_has_outline_pads_and_bend_lines_on_named_layers(design, exported):
    fab, index = exported
    for m, entry in zip(design.modules, index["modules"]):
        doc = ezdxf.readfile(fab / entry["files"]["dxf"])
        assert {"OUTLINE", "PADS", "BEND", "CONNECTOR"} <= {layer.dxf.name for layer in doc.layers}
        msp = doc.modelspace()
        ids, uv, _ = _taxels(design, m)
        circles = msp.query("CIRCLE[layer=='PADS']")
        centres = np.array([(c.dxf.center.x, c.dxf.center.y) for c in circles])
        assert np.abs(centres - uv * 1e3).max() < 2e-6  # y up in the DXF, pads in taxel order
        assert np.allclose([c.dxf.radius for c in circles], m.taxel_diameter * 500)
        (outline,) = msp.query("POLYLINE[layer=='OUTLINE']")
        assert outline.is_closed and np.allclose(np.ptp([(v.dxf.location.x, v.dxf.location.y) for v in outline.vertices], axis=0),
                                                 entry["outline_mm"])
        assert len(msp.query("SOLID[layer=='CONNECTOR']")) == len(ids) + 1
        bends = msp.query("LINE[layer=='BEND']")
        assert len(bends) == len(entry["bends"])
    # the wrapped module bends between each pair of columns by pitch / radius; the flat ones do not bend
    wrap = index["modules"][0]["bends"]
    assert [b["axis"] for b in wrap] == ["u"] * 3 and np.allclose([b["at_mm"] for b in wrap], [-10, 0, 10])
    assert np.allclose([b["angle_deg"] for b in wrap], np.degrees(0.01 / RADIUS), atol=1e-3)
    assert index["modules"][1]["bends"] == [] and index["modules"][2]["bends"] == []


def test_bom_index_svg_and_pdf(design, exported):
    fab, index = exported
    assert index["schema_version"] == 1 and index["map"] == "skin" and index["units"] == "mm"
    rows = list(csv.DictReader((fab / "bom.csv").open()))
    assert [int(r["module_id"]) for r in rows] == [0, 1, 2]
    assert [int(r["taxels"]) for r in rows] == [12, 5, 12] == [e["pads"] for e in index["modules"]]
    assert [int(r["connector_pins"]) for r in rows] == [13, 6, 13] and {r["connector_pitch_mm"] for r in rows} == {"0.5"}
    assert [[float(r["fpc_width_mm"]), float(r["fpc_height_mm"])] for r in rows] == [e["outline_mm"]
                                                                                  for e in index["modules"]]
    assert [r["link"] for r in rows] == ["link1", "link1", "link2"]
    for m, entry in zip(design.modules, index["modules"]):
        svg = ET.parse(fab / entry["files"]["svg"]).getroot()
        g = next(e for e in svg.iter() if e.get("id") == "pads")
        xy = np.array([[float(c.get("cx")), float(c.get("cy"))] for c in g])
        assert np.abs(xy - _taxels(design, m)[1] * [1e3, -1e3]).max() < 1e-3  # mm, y down as in KiCad
    pdf = (fab / "sheets.pdf").read_bytes()
    assert pdf.startswith(b"%PDF-1.4") and pdf.rstrip().endswith(b"%%EOF")
    offsets = [int(x) for x in re.findall(rb"(\d{10}) 00000 n", pdf)]
    assert all(re.match(rb"\d+ 0 obj", pdf[o:o + 12]) for o in offsets)  # the xref points at every object
    assert len(re.findall(rb"/Type /Page\b", pdf)) == 3
    first = re.search(rb"stream\n(.*?)\nendstream", pdf, re.S).group(1)
    assert b"(wrap \\(module 0\\)) Tj" in zlib.decompress(first)


@pytest.mark.parametrize("exchange", [True, False], ids=["renameat2", "moved-aside"])
def test_export_replaces_an_older_fab_folder_whole(design, tmp_path, capsys, monkeypatch, exchange):
    if not exchange:  # a system without an atomic exchange: the older folder is moved aside, then removed
        monkeypatch.setattr(fab_module, "_exchange", lambda a, b: False)
    path = taxel_map.save(design, tmp_path / "skin.json")
    out = tmp_path / "out"
    (out / "fab" / "m9_gone").mkdir(parents=True)
    (out / "fab" / "m9_gone" / "m9_gone.kicad_pcb").write_text("stale")
    (out / "fab" / "stale.txt").write_text("stale")
    assert main(["export", str(path), str(out), "--fab"]) == 0
    assert "3 FPC modules" in capsys.readouterr().out
    assert not (out / "fab" / "stale.txt").exists() and not (out / "fab" / "m9_gone").exists()
    assert sorted(q.name for q in out.iterdir()) == ["fab"]  # no scene, no temporary folder left
    index = json.loads((out / "fab" / "fab.json").read_text())
    listed = {"fab.json", "bom.csv", "sheets.pdf"} | {f for e in index["modules"] for f in e["files"].values()}
    assert {q.relative_to(out / "fab").as_posix() for q in (out / "fab").rglob("*") if q.is_file()} == listed


def test_bad_map_exits_1_with_one_line_and_keeps_the_old_files(design, tmp_path, capsys):
    out = tmp_path / "out"
    (out / "fab").mkdir(parents=True)
    (out / "fab" / "old.txt").write_text("kept")
    raw = json.loads(taxel_map.dumps(design))
    raw["modules"][2]["rows"] = 3  # the map's 12 taxels no longer fit the module's template
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(raw))
    (tmp_path / "broken.json").write_text("{")
    for path, words in ((bad, ["module 2 'ell'", "12 taxels", "re-place the module"]), (tmp_path / "broken.json",
                                                                                        ["not valid JSON"])):
        assert main(["export", str(path), str(out), "--fab"]) == 1
        cap = capsys.readouterr()
        lines = cap.err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("skinsafe export: ") and str(path) in lines[0], cap.err
        assert all(w in lines[0] for w in words), lines[0]
        assert "Traceback" not in cap.err and cap.out == ""
    assert (out / "fab" / "old.txt").read_text() == "kept" and sorted(q.name for q in out.iterdir()) == ["fab"]


def test_rect_union_traces_outer_loops_and_holes():
    (l_shape,) = rect_union(np.array([[0, 0, 2, 1], [0, 0, 1, 2]]))
    assert len(l_shape) == 6 and _area(l_shape) == pytest.approx(3)
    ring = rect_union(np.array([[0, 0, 3, 1], [0, 2, 3, 3], [0, 0, 1, 3], [2, 0, 3, 3]]))
    assert sorted(_area(q) for q in ring) == pytest.approx([-1, 9])  # the hole runs clockwise


def _area(loop) -> float:
    x, y = loop[:, 0], loop[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))

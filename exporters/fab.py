"""Fabrication files for every FPC module of a design: its flat pattern as a KiCad board, a DXF, an SVG, a
PDF page, plus one BOM and a `fab.json` index (`write_fab`; `skinsafe export MAP DIR --fab`).

The flat pattern (`flat_pattern`) is the module before it is wrapped: pad centres are the template's
(u, v) (`placement.template_grid`, in the order the module's taxels appear in the design), pads are
`taxel_diameter` discs, the outline is the union of the taxels' grid cells grown so no pad comes closer
than `margin` to the edge (squares of half-side max(pitch / 2, diameter / 2 + margin) around each pad;
for 'curve' the cells kept inside its outline), plus a tail leaving the lowest row (-v) that ends in an
edge-finger row for a 0.5 mm pitch FFC/FPC ZIF connector: pin k + 1 is the module's k-th taxel, the last
pin the common return. One net per taxel, named after where it ends: `B{board}_CH{channel:03d}`; the
return is `B{board}_COM`. Bend lines sit between neighbouring columns (or rows) whose wrapped normals
differ by more than `BEND_MIN_DEG`, labelled with the mean angle along them.

Conventions: KiCad and the SVG/PDF sheets are in mm with y down, x = 1000 u and y = -1000 v from the
module centre (KiCad adds `KICAD_ORIGIN_MM`); the DXF is in mm with y up (x = 1000 u, y = 1000 v).
"""
from __future__ import annotations

import csv
import io
import json
import logging
import os
import re
import shutil
import tempfile
import zlib
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from xml.sax.saxutils import escape

import numpy as np

from skinsafe.core.design.placement import module_grid, template_grid
from skinsafe.core.skin.model import DesignError, Module, SkinDesign

FAB_DIR = "fab"
SCHEMA_VERSION = 1
PIN_PITCH_MM = 0.5  # FFC/FPC ZIF connector pitch
FINGER_MM = (0.3, 3.0)  # edge finger width, length
FINGER_EDGE_MM = 0.2  # from the fingers' end to the tail's end
TAIL_SIDE_MM = 1.0  # copper-free border beside the finger row
TAIL_MM = 15.0  # from the body's edge to the tail's end
BEND_MIN_DEG = 3.0
KICAD_ORIGIN_MM = (100.0, 100.0)  # where the module centre sits on the KiCad page
CONNECTOR = "FFC/FPC ZIF connector, {pitch} mm pitch, {pins} positions"
DXF_LAYERS = {"OUTLINE": 7, "PADS": 1, "PAD_IDS": 8, "CONNECTOR": 2, "BEND": 5, "TEXT": 3}


@dataclass
class Bend:
    """A bend line: constant u (between two columns, axis 'u') or constant v (between two rows)."""

    axis: str
    at: float  # m
    span: tuple[float, float]  # m, along the other axis
    angle_deg: float  # mean over the neighbour pairs it separates
    max_deg: float


@dataclass
class FlatPattern:
    """One module flat, in m (u right, v up, module centre at 0)."""

    module: Module
    ids: np.ndarray  # (n,) taxel ids, template order
    board: np.ndarray  # (n,)
    channel: np.ndarray  # (n,)
    uv: np.ndarray  # (n, 2) pad centres
    loops: list[np.ndarray]  # closed outlines (k, 2), the first vertex not repeated
    fingers: np.ndarray  # (n + 1, 2) finger centres, pin 1 first
    bends: list[Bend]
    half: float  # half-side of a taxel's cell, m

    @property
    def key(self) -> tuple:
        """What the drawing of pads, outline and fingers depends on (modules alike share them)."""
        return self.uv.tobytes(), self.half, self.module.taxel_diameter

    @property
    def nets(self) -> list[str]:
        return [f"B{b}_CH{c:03d}" for b, c in zip(self.board.tolist(), self.channel.tolist())]

    @property
    def common(self) -> str:
        return f"B{self.module.board}_COM"

    @property
    def bounds(self) -> np.ndarray:
        """[[umin, vmin], [umax, vmax]] of the outline."""
        pts = np.concatenate(self.loops)
        return np.stack([pts.min(0), pts.max(0)])

    @property
    def size_mm(self) -> tuple[float, float]:
        lo, hi = self.bounds
        return round(float(hi[0] - lo[0]) * 1e3, 3), round(float(hi[1] - lo[1]) * 1e3, 3)


def flat_pattern(design: SkinDesign, module: Module) -> FlatPattern:
    """The module's flat pattern; DesignError when its taxels do not match its template."""
    m = module
    t = design.taxels
    idx = np.flatnonzero(t.module == m.id)
    grid = module_grid(m, len(idx))  # a mirrored module's pattern is the mirror image, in its taxels' order
    if grid is None:
        uv = template_grid(m, m.placement.get("outline"))[0]
        raise DesignError(f"module {m.id} '{m.name}': the map has {len(idx)} taxels on it but its {m.rows}x{m.cols} "
                          f"'{m.template}' template has {len(uv)}; re-place the module (or fix rows/cols) and save the map")
    uv, row, col = grid
    h = max(m.pitch / 2, m.taxel_diameter / 2 + m.margin)
    loops, fingers = _outline(uv.tobytes(), h)
    return FlatPattern(m, t.ids[idx], t.board[idx], t.channel[idx], uv, loops, fingers,
                       _bends(m, uv, row, col, t.frames[idx, :, 2], h), h)


@lru_cache(maxsize=64)
def _outline(uv_bytes: bytes, h: float):
    """Outline loops and finger centres around pads `uv` with cells of half-side h (modules alike share them)."""
    uv = np.frombuffer(uv_bytes).reshape(-1, 2)
    n_pins = len(uv) + 1
    low = uv[:, 1] <= uv[:, 1].min() + 1e-12
    cx = float(uv[low, 0].mean())
    width = (n_pins * PIN_PITCH_MM + 2 * TAIL_SIDE_MM) / 1e3
    bottom = float(uv[:, 1].min()) - h - TAIL_MM / 1e3
    rects = np.concatenate([np.concatenate([uv - h, uv + h], axis=1),
                            [[cx - width / 2, bottom, cx + width / 2, float(uv[:, 1].min()) - h]]])  # meets the row
    pin_u = cx + (np.arange(n_pins) - (n_pins - 1) / 2) * PIN_PITCH_MM / 1e3
    fingers = np.stack([pin_u, np.full(n_pins, bottom + (FINGER_EDGE_MM + FINGER_MM[1] / 2) / 1e3)], axis=1)
    loops = rect_union(rects)
    for a in loops + [fingers]:
        a.flags.writeable = False
    return loops, fingers


def _bends(m: Module, uv, row, col, z, h) -> list[Bend]:
    grid = np.full((m.rows, m.cols), -1)
    grid[row, col] = np.arange(len(uv))
    out = []
    for axis, a, b in (("u", grid[:, :-1], grid[:, 1:]), ("v", grid[:-1, :], grid[1:, :])):
        ok = (a >= 0) & (b >= 0)
        ang = np.zeros(a.shape)
        ang[ok] = np.degrees(np.arccos(np.clip(np.sum(z[a[ok]] * z[b[ok]], axis=1), -1.0, 1.0)))
        lines = ok.T if axis == "u" else ok  # one line per column boundary (u) or row boundary (v)
        angles = ang.T if axis == "u" else ang
        for k, (on, deg) in enumerate(zip(lines, angles)):
            if not on.any() or deg[on].mean() < BEND_MIN_DEG:
                continue
            first = (a.T if axis == "u" else a)[k][on]
            c = 0 if axis == "u" else 1
            at = float(uv[first[0], c] + m.pitch / 2)
            other = uv[first, 1 - c]
            out.append(Bend(axis, at, (float(other.min() - h), float(other.max() + h)),
                            float(deg[on].mean()), float(deg[on].max())))
    return out


def rect_union(rects: np.ndarray) -> list[np.ndarray]:
    """The boundary of a union of axis-aligned rectangles (k, 4: x0, y0, x1, y1) as closed loops, outer
    ones counter-clockwise, each vertex a corner (collinear points dropped)."""
    rects = np.round(np.asarray(rects, dtype=float), 12)
    xs, ys = np.unique(rects[:, [0, 2]]), np.unique(rects[:, [1, 3]])
    cov = np.zeros((len(xs) + 1, len(ys) + 1), bool)  # padded by one empty cell on each high side
    for x0, y0, x1, y1 in rects:
        cov[np.searchsorted(xs, x0):np.searchsorted(xs, x1), np.searchsorted(ys, y0):np.searchsorted(ys, y1)] = True
    pad = np.zeros((len(xs) + 2, len(ys) + 2), bool)
    pad[1:, 1:] = cov
    nxt: dict = {}  # directed boundary edges, inside on the left
    for i, j in zip(*np.nonzero(cov)):
        I, J = i + 1, j + 1
        if not pad[I, J - 1]:
            nxt.setdefault((i, j), []).append((i + 1, j))
        if not pad[I + 1, J]:
            nxt.setdefault((i + 1, j), []).append((i + 1, j + 1))
        if not pad[I, J + 1]:
            nxt.setdefault((i + 1, j + 1), []).append((i, j + 1))
        if not pad[I - 1, J]:
            nxt.setdefault((i, j + 1), []).append((i, j))
    loops = []
    while nxt:
        start = min(nxt)
        path, p = [start], start
        while True:
            q = nxt[p].pop()
            if not nxt[p]:
                del nxt[p]
            if q == start:
                break
            path.append(q)
            p = q
        pts = np.array(path)
        prev, after = np.roll(pts, 1, 0), np.roll(pts, -1, 0)
        (ax, ay), (bx, by) = (pts - prev).T, (after - pts).T
        turn = ax * by - ay * bx != 0  # a corner: the 2-D cross product (numpy 2 dropped 2-D np.cross)
        pts = pts[turn]
        loops.append(np.stack([xs[pts[:, 0]], ys[pts[:, 1]]], axis=1))
    return loops


# ---------------------------------------------------------------- KiCad


def _kicad(p: FlatPattern, robot: str) -> str:
    from kiutils.board import Board
    from kiutils.footprint import Attributes, Footprint, Pad
    from kiutils.items.common import Effects, Font, Justify, Net, Position, TitleBlock
    from kiutils.items.fpitems import FpText
    from kiutils.items.gritems import GrLine, GrText

    m, (ox, oy) = p.module, KICAD_ORIGIN_MM

    def at(u, v) -> Position:
        return Position(round(ox + float(u) * 1e3, 6), round(oy - float(v) * 1e3, 6))

    b = Board.create_new()
    b.general.thickness = 0.12
    b.setup.auxAxisOrigin, b.setup.gridOrigin = Position(ox, oy), Position(ox, oy)
    b.titleBlock = TitleBlock(title=f"FPC module {m.id} {m.name}",
                              comments={1: f"robot {robot}, link {m.body}, board {m.board}",
                                        2: f"{len(p.ids)} taxels, {m.taxel_diameter * 1e3:g} mm pads, "
                                           f"{PIN_PITCH_MM} mm pitch ZIF fingers"})
    names = p.nets
    nets = [Net(k + 1, name) for k, name in enumerate(names + [p.common])]
    b.nets.extend(nets)
    small = Effects(font=Font(height=1.0, width=1.0, thickness=0.15))
    template = _taxel_footprint(round(m.taxel_diameter * 1e3, 6))
    xy = np.round(np.array([ox, oy]) + p.uv * [1e3, -1e3], 6).tolist()
    taxels = "".join(template.format(x=x, y=y, id=tid, k=k + 1, net=names[k])
                     for k, (tid, (x, y)) in enumerate(zip(p.ids.tolist(), xy)))
    c = at(*p.fingers.mean(0))
    fp = Footprint(libraryNickname="skinsafe", entryName=f"FFC_edge_{PIN_PITCH_MM}mm_{len(p.fingers)}P", layer="F.Cu",
                   position=c, tedit="0", attributes=Attributes(type="smd"))
    fp.graphicItems += [FpText(type="reference", text="J1", position=Position(0, -FINGER_MM[1]), layer="F.Fab",
                               effects=small),
                        FpText(type="value", text=CONNECTOR.format(pitch=PIN_PITCH_MM, pins=len(p.fingers)),
                               position=Position(0, FINGER_MM[1]), layer="F.Fab", hide=True, effects=small)]
    for k, (u, v) in enumerate(p.fingers):
        q = at(u, v)
        fp.pads.append(Pad(number=str(k + 1), type="smd", shape="rect",
                           position=Position(round(q.X - c.X, 6), round(q.Y - c.Y, 6)), size=Position(*FINGER_MM),
                           layers=["F.Cu", "F.Mask"], net=nets[k]))
    b.footprints.append(fp)
    for loop in p.loops:
        for a, z in zip(loop, np.roll(loop, -1, 0)):
            b.graphicItems.append(GrLine(start=at(*a), end=at(*z), layer="Edge.Cuts", width=0.05))
    left = Effects(font=Font(height=1.2, width=1.2, thickness=0.18), justify=Justify(horizontally="left"))
    mid = Effects(font=Font(height=1.2, width=1.2, thickness=0.18))
    for bend in p.bends:
        s, e = _bend_ends(bend)
        b.graphicItems.append(GrLine(start=at(*s), end=at(*e), layer="Dwgs.User", width=0.1))
        b.graphicItems.append(GrText(text=_bend_text(bend), position=at(*_bend_label(bend)), layer="Dwgs.User",
                                     effects=mid if bend.axis == "u" else left))
    lo, hi = p.bounds
    for k, line in enumerate(_label(p, robot)):
        b.graphicItems.append(GrText(text=line, position=at(hi[0] + 0.003, hi[1] - 0.002 * k), layer="F.Fab",
                                     effects=left))
    b.graphicItems.append(GrText(text="stiffener: 0.3 mm total under the fingers (ZIF)",
                                 position=at(hi[0] + 0.003, lo[1] + 0.002), layer="F.Fab", effects=left))
    text = b.to_sexpr()
    at_connector = text.index('  (footprint "skinsafe:FFC_edge')  # the taxels' footprints go before it
    return text[:at_connector] + taxels + text[at_connector:]


@lru_cache(maxsize=16)
def _taxel_footprint(d: float) -> str:
    """A taxel's footprint (one round SMD pad of diameter d mm) as kiutils writes it, with {x} {y} (mm on the board),
    {id} (taxel id), {k} (net number) and {net} (net name) to fill: kiutils once per pad size, not per taxel."""
    from kiutils.footprint import Attributes, Footprint, Pad
    from kiutils.items.common import Effects, Font, Net, Position
    from kiutils.items.fpitems import FpText

    slot = {name: f"\x00{name}\x00" for name in ("x", "y", "id", "k", "net")}
    small = Effects(font=Font(height=1.0, width=1.0, thickness=0.15))
    fp = Footprint(libraryNickname="skinsafe", entryName="taxel_pad", layer="F.Cu",
                   position=Position(slot["x"], slot["y"]), tedit="0", attributes=Attributes(type="smd"))
    fp.graphicItems += [FpText(type="reference", text=f"T{slot['id']}", position=Position(0, 0), layer="F.Fab",
                               effects=small),
                        FpText(type="value", text=f"taxel {slot['id']} {slot['net']}", position=Position(0, d / 2 + 1),
                               layer="F.Fab", hide=True, effects=small)]
    fp.pads.append(Pad(number="1", type="smd", shape="circle", position=Position(0, 0), size=Position(d, d),
                       layers=["F.Cu", "F.Mask"], net=Net(slot["k"], slot["net"])))
    text = fp.to_sexpr(2, layerInFirstLine=True).replace("{", "{{").replace("}", "}}") + "\n"
    for name, mark in slot.items():
        text = text.replace(mark, "{" + name + "}")
    return text


def _bend_ends(bend: Bend):
    a, z = bend.span
    return ((bend.at, a), (bend.at, z)) if bend.axis == "u" else ((a, bend.at), (z, bend.at))


def _bend_label(bend: Bend):
    """Where the angle goes: centred above a constant-u line, right of a constant-v one."""
    return (bend.at, bend.span[1] + 0.0015) if bend.axis == "u" else (bend.span[1] + 0.001, bend.at)


def _bend_text(bend: Bend) -> str:
    return f"{bend.angle_deg:.1f}\N{DEGREE SIGN}"


def _id_size(radius: float, ids) -> float:
    """Text height (mm) of the pad ids: the longest fits across its pad (Helvetica digits are 0.556 em)."""
    longest = max((len(str(i)) for i in ids), default=1)
    return min(0.6 * radius, 2.0, 1.7 * radius / (0.556 * longest))


def _label(p: FlatPattern, robot: str) -> list[str]:
    m = p.module
    return [f"{m.name} (module {m.id})", f"link {m.body}, robot {robot}", f"{len(p.ids)} taxels, board {m.board}"]


# ---------------------------------------------------------------- DXF


def _dxf_preamble() -> str:
    """HEADER, TABLES (the named layers) and BLOCKS of an R12 DXF, written once by ezdxf."""
    import ezdxf

    log = logging.getLogger("ezdxf")
    level = log.level
    log.setLevel(logging.ERROR)  # R12 carries no $INSUNITS: ezdxf says so as it makes one
    try:
        doc = ezdxf.new("R12", setup=False)
    finally:
        log.setLevel(level)
    for name, color in DXF_LAYERS.items():
        doc.layers.add(name, color=color)
    buf = io.StringIO()
    doc.write(buf)
    text = buf.getvalue()
    return text[:text.index("  0\nSECTION\n  2\nENTITIES\n")]


def _memo(cache: dict | None, key, make):
    """make() once per key in `cache` (None: no cache)."""
    if cache is None:
        return make()
    if key not in cache:
        cache[key] = make()
    return cache[key]


def _mm(q) -> tuple[float, float]:
    return round(float(q[0]) * 1e3, 6), round(float(q[1]) * 1e3, 6)


def _r12(draw) -> str:
    """The DXF entities `draw(writer)` adds through ezdxf's fast R12 stream writer, without the section around."""
    from ezdxf.addons.r12writer import R12FastStreamWriter

    buf = io.StringIO()
    w = R12FastStreamWriter(buf)
    buf.seek(0)
    buf.truncate()
    draw(w)
    return buf.getvalue()


def _dxf_shape(w, p: FlatPattern) -> None:
    for loop in p.loops:
        w.add_polyline_2d([_mm(q) for q in loop], closed=True, layer="OUTLINE")
    for q in p.uv:
        w.add_circle(_mm(q), p.module.taxel_diameter * 500, layer="PADS")
    fw, fl = FINGER_MM[0] / 2, FINGER_MM[1] / 2
    for x, y in (_mm(q) for q in p.fingers):  # SOLID corners in zig-zag order
        w.add_solid([(x - fw, y - fl), (x + fw, y - fl), (x - fw, y + fl), (x + fw, y + fl)], layer="CONNECTOR")


def _dxf_texts(w, p: FlatPattern, robot: str) -> None:
    size = _id_size(p.module.taxel_diameter * 500, p.ids)
    for tid, q in zip(p.ids.tolist(), p.uv):
        w.add_text(str(tid), _mm(q), height=size, align="MIDDLE_CENTER", layer="PAD_IDS")
    for bend in p.bends:
        s, e = _bend_ends(bend)
        w.add_line(_mm(s), _mm(e), layer="BEND")
        w.add_text(_bend_text(bend).replace("\N{DEGREE SIGN}", "%%d"), _mm(_bend_label(bend)), height=1.2,
                   align="MIDDLE_CENTER" if bend.axis == "u" else "MIDDLE_LEFT", layer="BEND")
    lo, hi = p.bounds
    for k, line in enumerate(_label(p, robot)):
        w.add_text(line, _mm((hi[0] + 0.003, hi[1] - 0.002 * (k + 1))), height=1.2, layer="TEXT")


def _dxf(p: FlatPattern, robot: str, preamble: str, cache: dict | None = None) -> str:
    """The module in mm, y up: the layer tables, then entities through ezdxf's R12 stream writer."""
    shape = _memo(cache, ("dxf", p.key), lambda: _r12(lambda w: _dxf_shape(w, p)))
    texts = _r12(lambda w: _dxf_texts(w, p, robot))
    return f"{preamble}0\nSECTION\n2\nENTITIES\n{shape}{texts}0\nENDSEC\n0\nEOF\n"


# ---------------------------------------------------------------- sheets (SVG, PDF)


@dataclass
class Sheet:
    """A module's drawing in mm, y down: what the SVG and the PDF page show."""

    box: tuple[float, float, float, float]  # x0, y0, width, height
    loops: list[np.ndarray]
    pads: np.ndarray  # (n, 2)
    radius: float
    ids: list[str]
    fingers: np.ndarray  # (n + 1, 2)
    bends: list[tuple]  # (start, end, text, text position, centred), mm
    label: list[str]
    key: tuple  # FlatPattern.key: sheets alike share their drawing of outline, pads and fingers


def _sheet(p: FlatPattern, robot: str) -> Sheet:
    flip = np.array([1e3, -1e3])
    lo, hi = p.bounds * 1e3
    x0, y0 = lo[0] - 10, -hi[1] - 24  # room above for the label, below for the scale bar
    width, height = max(hi[0] - lo[0] + 20, 110.0), hi[1] - lo[1] + 24 + 14
    bends = [(tuple(np.multiply(s, flip)), tuple(np.multiply(e, flip)), _bend_text(b),
              tuple(np.multiply(_bend_label(b), flip)), b.axis == "u") for b in p.bends for s, e in [_bend_ends(b)]]
    return Sheet((x0, y0, width, height), [q * flip for q in p.loops], p.uv * flip, p.module.taxel_diameter * 500,
                 [str(i) for i in p.ids.tolist()], p.fingers * flip, bends,
                 _label(p, robot) + [f"FPC {p.size_mm[0]:.1f} x {p.size_mm[1]:.1f} mm, "
                                     f"{len(p.fingers)}-pin {PIN_PITCH_MM} mm ZIF fingers"], p.key)


def _f(v: float) -> str:
    return f"{v:.4f}".rstrip("0").rstrip(".")


def _svg_shape(s: Sheet) -> str:
    f, (fw, fl) = _f, FINGER_MM
    out = ['<g id="outline" fill="#f3e3b0" stroke="black" stroke-width="0.15">']
    out += [f'<path d="M{" L".join(f"{f(x)} {f(y)}" for x, y in loop)} Z"/>' for loop in s.loops]
    out.append('</g><g id="pads" fill="#d08040" stroke="none">')
    out += [f'<circle cx="{f(x)}" cy="{f(y)}" r="{f(s.radius)}"/>' for x, y in s.pads]
    out.append('</g><g id="connector" fill="#c8a000">')
    out += [f'<rect x="{f(x - fw / 2)}" y="{f(y - fl / 2)}" width="{f(fw)}" height="{f(fl)}"/>' for x, y in s.fingers]
    out.append("</g>")
    return "\n".join(out)


def _svg(s: Sheet, cache: dict | None = None) -> str:
    """The sheet as SVG, 1 user unit = 1 mm (printed at 100% it is 1:1)."""
    x0, y0, w, h = s.box
    f = _f
    out = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{f(w)}mm" height="{f(h)}mm" '
           f'viewBox="{f(x0)} {f(y0)} {f(w)} {f(h)}" font-family="Helvetica, Arial, sans-serif">',
           _memo(cache, ("svg", s.key), lambda: _svg_shape(s))]
    size = _id_size(s.radius, s.ids)
    out.append(f'<g id="pad-ids" font-size="{f(size)}" text-anchor="middle" dominant-baseline="central">')
    out += [f'<text x="{f(x)}" y="{f(y)}">{i}</text>' for i, (x, y) in zip(s.ids, s.pads)]
    out.append('</g><g id="bends" stroke="#2050c0" stroke-width="0.2" stroke-dasharray="1.5 0.8" fill="#2050c0" '
               'font-size="1.6">')
    for (a, b), (c, d), text, (x, y), centred in s.bends:
        out.append(f'<line x1="{f(a)}" y1="{f(b)}" x2="{f(c)}" y2="{f(d)}"/><text x="{f(x)}" y="{f(y)}" stroke="none" '
                   f'text-anchor="{"middle" if centred else "start"}" dominant-baseline="central">{escape(text)}</text>')
    out.append('</g><g id="label" font-size="3">')
    out += [f'<text x="{f(x0 + 5)}" y="{f(y0 + 6 + 4 * k)}">{escape(t)}</text>' for k, t in enumerate(s.label)]
    bx, by = x0 + 5, y0 + h - 6
    out.append(f'</g><g id="scale-bar"><rect x="{f(bx)}" y="{f(by)}" width="10" height="1" fill="black"/>'
               f'<text x="{f(bx + 12)}" y="{f(by + 1)}" font-size="3">10 mm</text></g></svg>\n')
    return "\n".join(out)


A4_PT = (595.276, 841.89)
PT = 72 / 25.4


def _pdf_page(s: Sheet, cache: dict | None = None) -> tuple[float, float, str]:
    """(width, height, content stream) of one A4 page showing the sheet at 1:1, or smaller to fit."""
    x0, y0, w, h = s.box
    pw, ph = A4_PT if h >= w else A4_PT[::-1]
    k = min(PT, (pw - 40) / w, (ph - 40) / h)  # points per mm
    tx, ty = 20 - x0 * k, ph - 20 + y0 * k

    def P(x, y) -> str:
        return f"{tx + x * k:.3f} {ty - y * k:.3f}"

    out = [_memo(cache, ("pdf", s.key), lambda: _pdf_shape(s, k, tx, ty, P))]
    size = _id_size(s.radius, s.ids) * k
    out.append(f"0 0 0 rg BT /F1 {size:.2f} Tf")
    for t, (x, y) in zip(s.ids, s.pads):  # digits are 0.556 em wide in Helvetica
        out.append(f"1 0 0 1 {tx + x * k - 0.278 * size * len(t):.3f} {ty - y * k - 0.35 * size:.3f} Tm ({t}) Tj")
    out.append("ET 0.125 0.314 0.753 RG 0.125 0.314 0.753 rg [4 2] 0 d")
    for a, e, text, (x, y), centred in s.bends:  # Helvetica: digits and '.' 0.556 / 0.278 em, the degree 0.4
        dx = -0.8 * (0.556 * (len(text) - 2) + 0.278 + 0.4) if centred else 0.0
        out.append(f"{P(*a)} m {P(*e)} l S BT /F1 {1.6 * k:.2f} Tf 1 0 0 1 {P(x + dx, y + 0.55)} Tm "
                   f"({_pdf_str(text)}) Tj ET")
    out.append("[] 0 d 0 0 0 rg BT /F1 9 Tf")
    out += [f"1 0 0 1 {P(x0 + 5, y0 + 6)} Tm 0 {-12 * i} Td ({_pdf_str(t)}) Tj" for i, t in enumerate(s.label)]
    scale = "1:1" if k >= PT - 1e-9 else f"1:{PT / k:.2f}"
    bx, by = x0 + 5, y0 + h - 6
    out.append(f"1 0 0 1 {P(bx + 12, by + 1)} Tm (10 mm, scale {scale}) Tj ET {P(bx, by + 1)} {10 * k:.3f} {k:.3f} re f")
    return pw, ph, "\n".join(out)


def _pdf_shape(s: Sheet, k: float, tx: float, ty: float, P) -> str:
    out = ["0.6 w 0 0 0 RG 0.953 0.890 0.690 rg"]
    for loop in s.loops:
        out.append(f"{P(*loop[0])} m " + " ".join(f"{P(x, y)} l" for x, y in loop[1:]) + " h B")
    out.append("0.816 0.502 0.251 rg")
    r, c = s.radius, 0.5523 * s.radius  # a circle as four Bezier quarters
    ring = np.array([(r, 0), (r, -c), (c, -r), (0, -r), (-c, -r), (-r, -c), (-r, 0), (-r, c), (-c, r), (0, r),
                     (c, r), (r, c), (r, 0)])
    pts = (s.pads[:, None, :] + ring) * [k, -k] + [tx, ty]
    circle = "%.3f %.3f m " + " ".join(["%.3f %.3f %.3f %.3f %.3f %.3f c"] * 4) + " f"
    out += [circle % tuple(q) for q in pts.reshape(len(pts), -1).tolist()]
    out.append("0.784 0.627 0 rg")
    fw, fl = FINGER_MM
    out += [f"{P(x - fw / 2, y + fl / 2)} {fw * k:.3f} {fl * k:.3f} re f" for x, y in s.fingers]
    return "\n".join(out)


def _pdf_str(t: str) -> str:
    return t.encode("latin-1", "replace").decode("latin-1").replace("\\", "\\\\").replace("(", "\\(").replace(")", "\\)")


def _pdf(pages: list[tuple[float, float, str]]) -> bytes:
    """A PDF of vector pages (Helvetica, compressed content streams)."""
    n = len(pages)
    objs = [b"<< /Type /Catalog /Pages 2 0 R >>",
            ("<< /Type /Pages /Kids [" + " ".join(f"{4 + 2 * i} 0 R" for i in range(n)) + f"] /Count {n} >>").encode(),
            b"<< /Type /Font /Subtype /Type1 /BaseFont /Helvetica /Encoding /WinAnsiEncoding >>"]
    for i, (w, h, content) in enumerate(pages):
        data = zlib.compress(content.encode("latin-1", "replace"), 6)
        objs.append(f"<< /Type /Page /Parent 2 0 R /MediaBox [0 0 {w:.3f} {h:.3f}] /Resources << /Font << /F1 3 0 R >> "
                    f">> /Contents {5 + 2 * i} 0 R >>".encode())
        objs.append(f"<< /Length {len(data)} /Filter /FlateDecode >>\nstream\n".encode() + data + b"\nendstream")
    out, offsets = bytearray(b"%PDF-1.4\n%\xe2\xe3\xcf\xd3\n"), []
    for k, body in enumerate(objs):
        offsets.append(len(out))
        out += f"{k + 1} 0 obj\n".encode() + body + b"\nendobj\n"
    xref = len(out)
    out += f"xref\n0 {len(objs) + 1}\n0000000000 65535 f \n".encode()
    out += b"".join(f"{o:010d} 00000 n \n".encode() for o in offsets)
    out += f"trailer\n<< /Size {len(objs) + 1} /Root 1 0 R >>\nstartxref\n{xref}\n%%EOF\n".encode()
    return bytes(out)


# ---------------------------------------------------------------- the folder


def _slug(m: Module) -> str:
    return f"m{m.id}_" + (re.sub(r"[^A-Za-z0-9_.-]+", "_", m.name).strip("._") or "module")


BOM_FIELDS = ["module_id", "module", "link", "board", "part", "fpc_width_mm", "fpc_height_mm", "taxels",
              "pad_diameter_mm", "pitch_mm", "connector", "connector_pins", "connector_pitch_mm", "folder"]


def write_fab(design: SkinDesign, out_dir: str | os.PathLike, name: str | None = None, source: str = "design") -> Path:
    """Write OUT_DIR/fab: per module a folder with its .kicad_pcb, .dxf and .svg; sheets.pdf (one page per
    module), bom.csv and fab.json (`name`: the map's name). Built beside it and swapped in whole, so an older
    fab folder is replaced, never mixed; DesignError (naming `source`) before anything is written."""
    design.validate(source)
    if not design.modules:
        raise DesignError(f"{source}: it has no modules; place modules on the robot before exporting fabrication files")
    robot = design.robot.name or design.robot.path or design.robot.kind
    try:
        patterns = [flat_pattern(design, m) for m in design.modules]
    except DesignError as e:
        raise DesignError(f"{source}: {e}") from None
    out_dir = Path(out_dir)
    target = out_dir / FAB_DIR
    if target.exists() and not target.is_dir():
        raise DesignError(f"{target} is a file; remove it or export into another folder")
    out_dir.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{FAB_DIR}.", dir=out_dir))
    try:
        preamble, pages, rows, index, cache = _dxf_preamble(), [], [], [], {}
        for p in patterns:
            m, slug = p.module, _slug(p.module)
            (tmp / slug).mkdir()
            files = {kind: f"{slug}/{slug}.{kind}" for kind in ("kicad_pcb", "dxf", "svg")}
            sheet = _sheet(p, robot)
            (tmp / files["kicad_pcb"]).write_text(_kicad(p, robot), encoding="utf-8")
            (tmp / files["dxf"]).write_text(_dxf(p, robot, preamble, cache), encoding="cp1252", errors="replace")
            (tmp / files["svg"]).write_text(_svg(sheet, cache), encoding="utf-8")
            pages.append(_pdf_page(sheet, cache))
            w, h = p.size_mm
            pins = len(p.fingers)
            connector = CONNECTOR.format(pitch=PIN_PITCH_MM, pins=pins)
            rows.append([m.id, m.name, m.body, m.board, f"FPC {w:.1f} x {h:.1f} mm, polyimide, 1 copper layer",
                         w, h, len(p.ids), round(m.taxel_diameter * 1e3, 3), round(m.pitch * 1e3, 3), connector, pins,
                         PIN_PITCH_MM, slug])
            index.append({"id": m.id, "name": m.name, "link": m.body, "board": m.board, "folder": slug,
                          "files": files, "page": len(pages), "outline_mm": [w, h], "pads": len(p.ids),
                          "connector": {"part": connector, "pins": pins, "common_pin": pins, "common_net": p.common},
                          "bends": [{"axis": b.axis, "at_mm": round(b.at * 1e3, 6), "angle_deg": round(b.angle_deg, 3),
                                     "max_deg": round(b.max_deg, 3)} for b in p.bends]})
        (tmp / "sheets.pdf").write_bytes(_pdf(pages))
        buf = io.StringIO()
        writer = csv.writer(buf, lineterminator="\n")
        writer.writerow(BOM_FIELDS)
        writer.writerows(rows)
        (tmp / "bom.csv").write_text(buf.getvalue(), encoding="utf-8")
        (tmp / "fab.json").write_text(json.dumps({
            "schema_version": SCHEMA_VERSION, "map": name or robot, "robot": robot, "units": "mm",
            "kicad": {"origin_mm": list(KICAD_ORIGIN_MM), "y_axis": "down"}, "dxf": {"y_axis": "up"},
            "connector_pitch_mm": PIN_PITCH_MM, "bom": "bom.csv", "sheets": "sheets.pdf",
            "modules": index}, indent=1) + "\n", encoding="utf-8")
        os.chmod(tmp, 0o755)
        _swap_in(tmp, target)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return target


def _swap_in(new: Path, target: Path) -> None:
    """Put the folder `new` at `target`: exchanged in one step where the system can (Linux), else the older
    target moved aside first; the older one is removed after."""
    if target.exists() and _exchange(new, target):
        shutil.rmtree(new, ignore_errors=True)  # now the older folder
        return
    old = None
    if target.exists():
        old = Path(tempfile.mkdtemp(prefix=f".{FAB_DIR}.old.", dir=target.parent))
        os.replace(target, old / FAB_DIR)
    try:
        os.replace(new, target)
    except BaseException:
        if old is not None:
            os.replace(old / FAB_DIR, target)
        raise
    finally:
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)


def _exchange(a: Path, b: Path) -> bool:
    """Swap two paths atomically (renameat2 with RENAME_EXCHANGE); False where the system cannot."""
    import ctypes

    try:
        fn = ctypes.CDLL(None, use_errno=True).renameat2
    except (OSError, AttributeError):
        return False
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    at_fdcwd, rename_exchange = -100, 2
    return fn(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), rename_exchange) == 0


def count_files(folder: Path) -> int:
    """How many files lie in `folder` and below."""
    return sum(1 for q in folder.rglob("*") if q.is_file())



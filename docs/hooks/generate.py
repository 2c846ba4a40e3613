"""mkdocs hook: the pages generated from the code (the CLI reference from argparse) and the source
layout mkdocstrings reads (`skinsafe.core` lives in core/, and so on)."""
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = {"core": "core", "exporters": "exporters", "hardware": "hardware", "addon": "addon"}


def _api_source() -> None:
    """build/api-src/skinsafe/{core,...} -> the folders (made on import: mkdocstrings reads the path first)."""
    src = ROOT / "build" / "api-src" / "skinsafe"
    src.mkdir(parents=True, exist_ok=True)
    (src / "__init__.py").write_text('"""skinsafe: whole-body tactile skins, from Blender to the robot."""\n')
    for name, folder in PACKAGES.items():
        link = src / name
        if not link.is_symlink():
            link.symlink_to(ROOT / folder, target_is_directory=True)


_api_source()


def on_page_markdown(markdown, page, config, files):
    if "<!-- cli-reference -->" in markdown:
        from skinsafe.core.app.cli import reference_markdown

        markdown = markdown.replace("<!-- cli-reference -->", reference_markdown())
    return _assets_from(markdown, page)


ASSETS = ("results/", "blend_assets/")
ASSET_REF = re.compile(r'(\]\(|src=")((?:results|blend_assets)/[^)"\s]+)')


def on_files(files, config):
    """The pictures pages show from results/ and blend_assets/ and the results files (not an experiment's per-task
    files) that tables link to for their full rows, served at the same paths, the state machine's
    picture drawn from its edges (docs/hooks/state_machine.mmd: img/state_machine.png) and DIAGRAMS
    (img/NAME.png)."""
    from mkdocs.structure.files import File

    generated = ROOT / "build" / "docs-img"
    state_picture(STATE_MACHINE.read_text(), generated / "img" / "state_machine.png")
    files.append(File("img/state_machine.png", str(generated), config["site_dir"], config["use_directory_urls"]))
    for name, (nodes, edges, size) in DIAGRAMS.items():
        flow_picture(nodes, edges, size, generated / "img" / f"{name}.png")
        files.append(File(f"img/{name}.png", str(generated), config["site_dir"], config["use_directory_urls"]))

    served = [p for folder in ("results", "blend_assets/pictures") for p in sorted((ROOT / folder).rglob("*.png"))]
    served += [p for p in sorted((ROOT / "results").rglob("*.json")) if "tasks" not in p.parts]  # a table's full rows
    for path in served:
        files.append(File(path.relative_to(ROOT).as_posix(), str(ROOT), config["site_dir"], config["use_directory_urls"]))
    return files


def _assets_from(markdown: str, page) -> str:
    """`results/x.png` in a page at docs/a/b.md points to the site root's results/x.png."""
    up = "../" * page.file.src_uri.count("/")
    return ASSET_REF.sub(lambda m: m.group(1) + up + m.group(2), markdown)


STATE_MACHINE = Path(__file__).with_name("state_machine.mmd")  # a mermaid stateDiagram's edges
EDGE = re.compile(r"^\s*(\S+)\s*-->\s*(\S+?)(?::\s*(.*))?$")
STATE_XY = {"[*]": (-1.6, 3), "preflight": (0, 3), "armed": (3, 3), "moving": (6.2, 3), "retracting": (6.2, 0.8),
            "protective_stop": (3, -0.3), "ended": (10, 1.4)}


def state_picture(source: str, path: Path) -> None:
    """A PNG of a mermaid stateDiagram's edges (docs/hooks/state_machine.mmd), for readers without the mermaid
    script."""

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import FancyArrowPatch

    edges = [m.groups() for m in map(EDGE.match, source.splitlines()) if m]
    fig, ax = plt.subplots(figsize=(12, 7))
    names = list(dict.fromkeys(n for a, b, _ in edges for n in (a, b)))
    xy = {n: STATE_XY.get(n, (i * 1.5, -1.2)) for i, n in enumerate(names)}
    for n, (x, y) in xy.items():
        start = n == "[*]"
        ax.text(x, y, "" if start else n.replace("_", " "), ha="center", va="center", fontsize=11,
                bbox=dict(boxstyle="circle" if start else "round,pad=0.5", fc="black" if start else
                          ("#f4c7c3" if n == "protective_stop" else "#d9ead3"), ec="black"))
    count: dict = {}
    legend: list[str] = []
    for a, b, label in edges:
        (x0, y0), (x1, y1) = xy[a], xy[b]
        if b == "[*]":
            continue
        k = count[frozenset((a, b))] = count.get(frozenset((a, b)), -1) + 1
        rad = 0.1 + 0.22 * k
        ax.add_patch(FancyArrowPatch((x0, y0), (x1, y1), connectionstyle=f"arc3,rad={rad}", arrowstyle="-|>",
                                     mutation_scale=14, shrinkA=30, shrinkB=30, color="#444"))
        if label:  # a number at the arc's middle (the Bezier's control point is mid + rad * (dy, -dx)), the text below
            legend.append(label)
            mx, my = (x0 + x1) / 2 + 0.5 * rad * (y1 - y0), (y0 + y1) / 2 - 0.5 * rad * (x1 - x0)
            ax.text(mx, my, str(len(legend)), ha="center", va="center", fontsize=8, fontweight="bold",
                    bbox=dict(boxstyle="circle,pad=0.25", fc="white", ec="#444"))
    ax.text(-1.8, -0.9, "\n".join(f"{i}. {t}" for i, t in enumerate(legend, 1)), ha="left", va="top", fontsize=8.5)
    ax.set_xlim(-2.0, 11.8)
    ax.set_ylim(-0.6 - 0.32 * len(legend), 3.6)
    ax.axis("off")
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)


# Box-and-arrow pictures: name -> (nodes {id: (x, y, label)}, edges [(a, b, label)], figure size in inches)
DIAGRAMS = {
    "pipeline": ({
        "addon": (0, 2, "Blender add-on\n(addon/)"), "cli": (0, 0, "skinsafe design / sample\n(core/design)"),
        "map": (3.2, 1, "skin design\n= taxel map (JSON)\n(core/skin)"),
        "mjcf": (6.5, 2.6, "MuJoCo scene (MJCF)\n(exporters/)"), "sim": (11, 2.6, "contacts, the three layers,\n"
                                                                            "experiments (core/sim, safety)"),
        "boards": (6.5, -0.6, "interface boards\n(hardware/: deploy)"),
        "runtime": (10.5, 0.6, "the runtime (core/runtime):\nboards -> layers -> robot"),
        "robot": (15.2, 0.6, "robot driver:\nMuJoCo sim or FR3")},
        [("addon", "map", "export"), ("cli", "map", "save"), ("map", "mjcf", "skinsafe export"), ("mjcf", "sim", ""),
         ("map", "boards", "skinsafe deploy"), ("boards", "runtime", "serial frames"), ("map", "runtime", ""),
         ("runtime", "robot", "joint velocity")], (14, 5)),
    "tick": ({
        "clock": (0, 2, "the robot's clock\n(driver: sim 2 ms step,\nlibfranka 1 kHz)"),
        "read": (3.6, 2, "newest readings\n(shared memory;\nnever waits)"),
        "watch": (7.2, 2, "watchdogs -> monitor\n(a fault: protective\nstop, named)"),
        "stack": (10.8, 2, "SafetyStack.tick\n(strategy, modulation,\ndefensiveness)"),
        "limit": (10.8, 0, "limiter\n(the robot's q, qd, qdd\nlimits)"),
        "send": (7.2, 0, "driver.send\n(joint velocity)"),
        "tap": (3.6, 0, "Tick record -> recorder,\nlive view (copies;\nmay drop frames)"),
        "reader": (3.6, 4, "reader process: epoll on\nevery board's port, decode,\ntare (hardware/skin_reader)")},
        [("clock", "read", "tick"), ("reader", "read", "latest force per taxel"), ("read", "watch", ""),
         ("watch", "stack", "measured dt, q, qd"), ("stack", "limit", "command"), ("limit", "send", "what is sent"),
         ("send", "tap", "what is logged")], (13, 6)),
    "data_model": ({
        "design": (0, 2, "SkinDesign\n(one per skin)"), "robot": (-3.4, 3.6, "RobotRef\n(builtin, URDF, MJCF)"),
        "bodies": (-3.4, 0.4, "bodies\n(the skinned links)"),
        "modules": (3.4, 3.6, "Module\n(one FPC: rows x cols pads,\non one body, read by one board)"),
        "boards": (7.2, 2, "Board\n(uid, channel capacity)"),
        "taxels": (3.4, 0.4, "Taxels (arrays of N)\nids, positions, frames, area,\nthresholds, enabled")},
        [("design", "robot", "for"), ("design", "bodies", ""), ("design", "modules", ""), ("design", "taxels", ""),
         ("modules", "boards", "board"), ("taxels", "modules", "module"), ("taxels", "boards", "board, channel"),
         ("taxels", "bodies", "body")], (13, 5)),
    "deploy": ({
        "find": (0, 0, "find boards\n(--all: every serial port,\nidentify by unique id)"),
        "check": (3.4, 0, "refuse a misfit\n(uid, channels, firmware,\nchunk size, streaming)"),
        "push": (6.8, 0, "push the board's part\nof the map in chunks"),
        "commit": (10.2, 0, "commit with its SHA-256\n(old or new config,\nnever a mix)"),
        "verify": (13.6, 0, "read back and\ncompare hashes\n(one line per board)")},
        [("find", "check", ""), ("check", "push", ""), ("push", "commit", ""), ("commit", "verify", "")], (15, 2.2)),
}


def flow_picture(nodes: dict, edges: list, size: tuple, path: Path) -> None:
    """A PNG of boxes (id -> x, y, label) joined by labelled arrows."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import FancyArrowPatch

    fig, ax = plt.subplots(figsize=size)
    box = {n: ax.text(x, y, label, ha="center", va="center", fontsize=10, zorder=2,
                      bbox=dict(boxstyle="round,pad=0.5", fc="#d9ead3", ec="black")) for n, (x, y, label) in nodes.items()}
    fig.canvas.draw()  # the boxes' outlines exist once drawn: the arrows end at them
    for a, b, label in edges:
        (x0, y0, _), (x1, y1, _) = nodes[a], nodes[b]
        ax.add_patch(FancyArrowPatch((x0, y0), (x1, y1), arrowstyle="-|>", mutation_scale=16, shrinkA=2, shrinkB=2,
                                     patchA=box[a].get_bbox_patch(), patchB=box[b].get_bbox_patch(), color="#444", zorder=3))
        if label:
            ax.text((x0 + x1) / 2, (y0 + y1) / 2, label, ha="center", va="center", fontsize=8.5, style="italic",
                    bbox=dict(boxstyle="round,pad=0.2", fc="white", ec="none"))
    xs, ys = [n[0] for n in nodes.values()], [n[1] for n in nodes.values()]
    ax.set_xlim(min(xs) - 1.5, max(xs) + 1.5)
    ax.set_ylim(min(ys) - 0.9, max(ys) + 0.9)
    ax.axis("off")
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100, bbox_inches="tight")
    plt.close(fig)

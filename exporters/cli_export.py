"""`skinsafe export MAP OUT_DIR`: a taxel map to a MuJoCo scene folder (scene.xml, meshes/, taxel_map.json),
with `--urdf` also robot_skin.urdf and its own robot_skin_meshes/ (robot tree, taxel links, tactile sensors) for ROS;
with `--fab` only OUT_DIR/fab/, the FPC modules' fabrication files (`exporters.fab`), and no scene."""
from __future__ import annotations

import sys
from pathlib import Path

from skinsafe.core.robot.models import load_robot
from skinsafe.core.sim.scene import COLLISION_MODES, Obstacle, SceneOptions
from skinsafe.core.skin import taxel_map
from skinsafe.core.skin.model import DesignError
from skinsafe.exporters.fab import FAB_DIR, PIN_PITCH_MM, count_files, write_fab
from skinsafe.exporters.mjcf import export_scene
from skinsafe.exporters.urdf import URDF_FILE, build_urdf, mesh_dir_of, write_urdf


def add_arguments(p) -> None:
    d = SceneOptions()
    p.add_argument("map", help="taxel map JSON (from the add-on or `skinsafe sample`)")
    p.add_argument("out_dir", help="folder to write scene.xml, meshes/ and taxel_map.json into")
    p.add_argument("--collision", choices=COLLISION_MODES, default=d.collision,
                   help="collision model: 'skin' fits it to the skin (default %(default)s); the others simplify mesh robots")
    p.add_argument("--target-faces", type=int, default=d.target_faces, help="faces for --collision decimate")
    p.add_argument("--no-visual", action="store_true", help="drop visual-only meshes")
    p.add_argument("--no-sites", action="store_true", help="no taxel sites")
    p.add_argument("--touch", action="store_true", help="add one MuJoCo touch sensor per taxel (slow reference)")
    p.add_argument("--no-prune", action="store_true", help="keep contacts on bodies nothing can touch")
    p.add_argument("--timestep", type=float, default=None, help="physics timestep, s (default: the robot's)")
    p.add_argument("--probe", type=float, default=None, metavar="RADIUS",
                   help="add a mocap sphere 'probe' of this radius (m) to poke the skin with")
    p.add_argument("--urdf", action="store_true",
                   help=f"also write OUT_DIR/{URDF_FILE}: the robot, one fixed link per taxel, tactile sensors (ROS)")
    p.add_argument("--fab", action="store_true",
                   help=f"write only OUT_DIR/{FAB_DIR}/, quickly and without the scene: per FPC module its flat pattern "
                        f"as a KiCad board (mm, y down), DXF and SVG, one PDF page each, bom.csv and fab.json "
                        f"({PIN_PITCH_MM} mm pitch ZIF edge fingers); an older {FAB_DIR}/ is replaced whole")


def run_fab(args) -> int:
    """`--fab`: the map's fabrication files into OUT_DIR/fab (no robot, no scene)."""
    if args.urdf:
        print("skinsafe export: --fab writes only the fabrication files; run the export once with --fab and once "
              "with --urdf", file=sys.stderr)
        return 1
    path = Path(args.map)
    try:
        design = taxel_map.load(path)
        fab = write_fab(design, args.out_dir, name=path.stem, source=str(path))
    except (DesignError, ValueError) as e:
        print(f"skinsafe export: {e}", file=sys.stderr)
        return 1
    except OSError as e:
        print(f"skinsafe export: cannot write {e.filename or args.out_dir}: {e.strerror}; pick a folder you can write",
              file=sys.stderr)
        return 1
    n = len(design.modules)
    print(f"wrote {fab}: {n} FPC module{'s' * (n != 1)} ({design.n_taxels} taxels), {count_files(fab)} files "
          f"(fab.json, bom.csv, sheets.pdf, a .kicad_pcb, .dxf and .svg per module)")
    return 0


def run(args) -> int:
    if getattr(args, "fab", False):
        return run_fab(args)
    path = Path(args.map)
    try:
        design = taxel_map.load(path)
        robot = load_robot(design.robot, base_dir=path.parent)
        options = SceneOptions(collision=args.collision, target_faces=args.target_faces, visual=not args.no_visual,
                                taxel_sites=not args.no_sites, touch_sensors=args.touch,
                                prune_contacts=not args.no_prune, timestep=args.timestep)
        obstacles = [Obstacle("probe", "sphere", (args.probe,), pos=(0, 0, -1), mocap=True)] if args.probe else []
        meshes: dict = {}
        # checked before anything is written; its meshes go in a folder of its own, never the scene's
        urdf = build_urdf(design, robot, meshes=meshes, mesh_dir=mesh_dir_of(URDF_FILE)) if args.urdf else None
        scene = export_scene(design, robot, args.out_dir, obstacles, options)
        if urdf is not None:
            write_urdf(Path(args.out_dir) / URDF_FILE, urdf, meshes)
    except (DesignError, ValueError) as e:
        print(f"skinsafe export: {e}", file=sys.stderr)
        return 1
    print(f"wrote {scene} ({design.n_taxels} taxels on {len(design.bodies)} bodies) and "
          f"{Path(args.out_dir) / 'taxel_map.json'}" + (f" and {Path(args.out_dir) / URDF_FILE}" if args.urdf else ""))
    return 0

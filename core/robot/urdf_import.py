"""Robots from their ROS description as users have it: URDF or xacro, `package://` and relative
mesh paths resolved against package roots the user names, STL, OBJ and DAE meshes.

MuJoCo's URDF reader parses the kinematic tree and the primitive shapes (links joined by fixed
joints stay their own bodies, visual geometry is kept). Meshes never go through MuJoCo's file
decoders (they have none for Collada): every mesh is loaded here with trimesh (pycollada for
.dae), validated once, and handed to the spec as vertices and faces. Visual meshes become
non-colliding geoms in group `VISUAL_GROUP`, collision meshes colliding geoms in group
`COLLISION_GROUP`. Every error names the link and the file.
"""
from __future__ import annotations

import contextlib
import re
import xml.etree.ElementTree as ET
from pathlib import Path

import mujoco
import numpy as np
from scipy.spatial.transform import Rotation

from skinsafe.core.robot.array_cache import load_pieces, save_pieces
from skinsafe.core.robot.meshes import load_checked
from skinsafe.core.skin.model import DesignError

URDF_JOINTS = ("revolute", "continuous", "prismatic", "fixed")
MESH_FORMATS = (".stl", ".obj", ".dae", ".ply", ".off", ".glb", ".gltf")
VISUAL_GROUP = 1
COLLISION_GROUP = 3


def package_roots(dirs) -> dict[str, Path]:
    """ROS package name -> folder, from folders that are packages or hold packages (3 levels deep).
    A package is a folder with a package.xml (its <name>, else the folder name)."""
    roots: dict[str, Path] = {}
    for d in dirs or ():
        d = Path(d).resolve()
        if not d.is_dir():
            raise DesignError(f"robot: package folder '{d}' does not exist; give a folder that is a ROS package "
                              "(has package.xml) or holds packages")
        found = [d / "package.xml"] if (d / "package.xml").is_file() else \
            sorted(p for k in (1, 2, 3) for p in d.glob("/".join(["*"] * k) + "/package.xml"))
        for pkg_xml in found:
            try:
                name = (ET.parse(pkg_xml).getroot().findtext("name") or "").strip()
            except ET.ParseError:
                name = ""
            roots.setdefault(name or pkg_xml.parent.name, pkg_xml.parent)
            roots.setdefault(pkg_xml.parent.name, pkg_xml.parent)
    return roots


def resolve_uri(uri: str, base: Path, roots: dict[str, Path], where: str) -> Path:
    """The file a URDF mesh filename names: `package://pkg/rel`, `file://abs`, or relative to the URDF."""
    if uri.startswith("package://"):
        pkg, _, rel = uri[len("package://"):].partition("/")
        if pkg not in roots:
            raise DesignError(f"{where}: mesh '{uri}' is in ROS package '{pkg}', which is not among the package "
                              f"folders given ({sorted(roots) or 'none'}); pass its folder with --package-dir")
        path = roots[pkg] / rel
    elif uri.startswith("file://"):
        path = Path(uri[len("file://"):])
    else:
        path = Path(uri) if Path(uri).is_absolute() else base / uri
    if not path.is_file():
        raise DesignError(f"{where}: mesh file '{uri}' not found at '{path}'; fix the filename or the package folder")
    if path.suffix.lower() not in MESH_FORMATS:
        raise DesignError(f"{where}: mesh file '{path}' has format '{path.suffix}'; use one of {', '.join(MESH_FORMATS)}")
    return path


@contextlib.contextmanager
def _xacro_find(roots: dict[str, Path]):
    """xacro's `$(find pkg)` answered from the given package folders (no ROS install needed)."""
    from xacro import substitution_args as sa

    def find(pkg):
        if pkg not in roots:
            raise DesignError(f"xacro: $(find {pkg}) names a ROS package that is not among the package folders "
                              f"given ({sorted(roots) or 'none'}); pass its folder with --package-dir")
        return str(roots[pkg])

    old = sa._eval_find
    sa._eval_find = find
    try:
        yield
    finally:
        sa._eval_find = old


def expand(path: Path, roots: dict[str, Path], args: dict | None = None) -> str:
    """The URDF text of `path`: xacro files are expanded (with `args` as `name:=value`)."""
    text = path.read_text()
    if not (path.suffix == ".xacro" or "ros.org/wiki/xacro" in text[:2000]):
        return text
    import xacro

    try:
        with _xacro_find(roots):
            doc = xacro.process_file(str(path), mappings={k: str(v) for k, v in (args or {}).items()})
    except DesignError:
        raise
    except Exception as e:  # xacro raises its own exception kinds and XacroException
        ours = _wrapped_design_error(e)  # our own $(find) refusal, which xacro wraps with its text repeated
        if ours is not None:
            raise DesignError(f"robot file '{path}': {ours}") from None
        said = " ".join(str(e).split())  # one line: xacro's messages span lines
        raise DesignError(f"robot file '{path}': xacro failed ({type(e).__name__}: {said}); "
                          f"{_arg_hint(str(e), xacro_args_declared(path), args or {})}") from None
    return doc.toxml()


def _wrapped_design_error(e: BaseException) -> DesignError | None:
    """The DesignError inside xacro's exception chain (`XacroException.exc`, causes), if any."""
    seen = set()
    while e is not None and id(e) not in seen:
        if isinstance(e, DesignError):
            return e
        seen.add(id(e))
        e = getattr(e, "exc", None) or e.__cause__ or e.__context__
    return None


def _arg_hint(error: str, declared: dict, given: dict) -> str:
    """The fix for a failed xacro expansion, naming the argument at fault where one can be told:
    one xacro found unset, or, for a file not found, one whose value is the path's first missing
    part (else the arguments left empty by default, which build such paths)."""
    fix = "set it with --xacro-arg NAME:=VALUE"
    unset = re.search(r"[Uu]ndefined substitution argument (\S+)", error)
    if unset:
        name = unset.group(1)
        return f"xacro argument '{name}' is not set where the file first reads it: pass --xacro-arg {name}:=VALUE"
    values = {k: (str(given[k]), "given") if k in given else (v, "its default")
              for k, v in declared.items() if k in given or v is not None}
    missing = re.search(r"No such file or directory: '?([^'\s]+)", error)
    if missing:
        path = Path(missing.group(1))
        part = next((p.name for p in reversed(path.parents) if p != Path(p.anchor) and not p.exists()), path.name)
        named = [f"'{k}' is '{v}' ({how})" for k, (v, how) in values.items() if v == part] or \
            [f"'{k}' is '{v}' ({how})" for k, (v, how) in values.items() if len(v) > 2 and v in part]
        if named:
            return f"'{part}' in the missing path comes from xacro argument {', '.join(named)}: {fix}"
        empty = sorted((k for k, (v, how) in values.items() if v == "" and how == "its default"),
                       key=lambda k: k not in part)
        if empty:
            return (f"'{part}' in the missing path is built from an argument left empty by default "
                    f"({', '.join(empty)}): {fix}")
    return f"check the file and its arguments (this file declares {', '.join(declared) or 'none'})"


def parse_xacro_args(items, where: str = "xacro arguments") -> dict[str, str]:
    """`NAME:=VALUE` items (a list, or one string separated by ';' or spaces) as a dict; DesignError
    naming the item that is not NAME:=VALUE."""
    if isinstance(items, str):
        items = [a for a in re.split(r"[;\s]+", items) if a]
    bad = [a for a in items if ":=" not in a or not a.split(":=", 1)[0].strip()]
    if bad:
        raise DesignError(f"{where}: '{bad[0]}' is not NAME:=VALUE (e.g. ur_type:=ur5e)")
    return {k.strip(): v.strip() for k, v in (a.split(":=", 1) for a in items)}


def _origin(el) -> tuple[list[float], list[float]]:
    o = el.find("origin") if el is not None else None
    xyz = [float(v) for v in (o.get("xyz", "0 0 0") if o is not None else "0 0 0").split()]
    rpy = [float(v) for v in (o.get("rpy", "0 0 0") if o is not None else "0 0 0").split()]
    q = Rotation.from_euler("xyz", rpy).as_quat()  # URDF rpy: fixed axes x, y, z
    return xyz, [q[3], q[0], q[1], q[2]]


def check_joints(root: ET.Element, src: str) -> None:
    for j in root.findall("joint"):  # the robot's joints (a <transmission> names joints too)
        if j.get("type") not in URDF_JOINTS:
            raise DesignError(f"robot file '{src}': joint '{j.get('name')}' has type '{j.get('type')}', which skinsafe "
                              f"does not support; use one of {', '.join(URDF_JOINTS)}")


def links_without_inertia(root: ET.Element) -> list[str]:
    """Moving links whose mass MuJoCo would guess: a link moved by a joint that, with the links
    welded to it by fixed joints, carries geometry but no <inertial>."""
    links = {link.get("name"): link for link in root.findall("link")}
    parent = {j.find("child").get("link"): (j.find("parent").get("link"), j.get("type"))
              for j in root.findall("joint") if j.find("child") is not None and j.find("parent") is not None}

    def group(name):  # the link a fixed-joint chain hangs from (its weld root), None for the base
        while name in parent and parent[name][1] == "fixed":
            name = parent[name][0]
        return name if name in parent else None

    groups: dict[str, list] = {}
    for name, link in links.items():
        g = group(name)
        if g is not None:
            groups.setdefault(g, []).append(link)
    return [g for g, members in groups.items()
            if not any(m.find("inertial") is not None for m in members)
            and any(m.find("visual") is not None or m.find("collision") is not None for m in members)]


def xacro_args_declared(path: Path) -> dict[str, str | None]:
    """The arguments a xacro file declares (`<xacro:arg name=... default=...>`): name -> default
    (None when it has none), for messages."""
    try:
        root = ET.parse(path).getroot()
    except (ET.ParseError, OSError):
        return {}
    return {el.get("name"): el.get("default") for el in root.iter() if el.tag.endswith("}arg") and el.get("name")}


def xacro_arg_names(path: Path) -> list[str]:
    """The arguments a xacro file declares, for messages."""
    return list(xacro_args_declared(path))


def _moving_links(root: ET.Element) -> set[str]:
    return {j.find("child").get("link") for j in root.findall("joint")
            if j.get("type") != "fixed" and j.find("child") is not None}


def with_inertials(path: Path, roots: dict[str, Path], args: dict, root: ET.Element) -> ET.Element:
    """Where a xacro file's expansion leaves moving links without <inertial>, the file is expanded
    again with each switch it declares off (default 'false') that the user left unset turned on,
    one at a time; the first that gives every moving link its inertial and moves the same links
    is taken (the Franka description adds its inertials only with gazebo:=true; without them MuJoCo
    guesses 92 kg for the 16.7 kg arm); else `root` as it was."""
    if not links_without_inertia(root):
        return root
    for name, default in xacro_args_declared(path).items():
        if default != "false" or name in args:
            continue
        try:
            other = _urdf_root(path, roots, {**args, name: "true"})
        except DesignError:
            continue
        if not links_without_inertia(other) and _moving_links(other) == _moving_links(root):
            return other
    return root


def _urdf_root(path: Path, roots: dict[str, Path], args: dict) -> ET.Element:
    try:
        root = ET.fromstring(expand(path, roots, args))
    except ET.ParseError as e:
        raise DesignError(f"robot file '{path}': not valid XML ({e}); check the file") from None
    if root.tag != "robot":
        raise DesignError(f"robot file '{path}': top element is <{root.tag}>, expected <robot>; is it a URDF?")
    return root


MESH_CACHE_VERSION = 1  # part of every repaired mesh's key: bump it when load_checked's repair changes


def _checked_mesh(file: Path, where: str, scale: list[float]) -> tuple[np.ndarray, np.ndarray]:
    """A mesh file's repaired vertices (scaled) and faces (`load_checked`), kept on disk by a digest of the
    file's bytes and the scale (`array_cache`): parsing and repairing a robot's Collada visuals takes
    seconds, and a design, its exports and its runs load the same robot again and again."""
    import hashlib

    file = Path(file)
    key = "mesh-" + hashlib.sha1(file.read_bytes() + np.asarray([*scale, MESH_CACHE_VERSION], float).tobytes())\
        .hexdigest() if file.is_file() else None  # a missing file: load_checked names it
    kept = load_pieces(key) if key else None
    if kept is not None:
        return kept[0], kept[1].astype(np.int64)
    mesh = load_checked(file, where, manifold=False)
    if scale != [1, 1, 1]:
        mesh.apply_scale(scale)
    vertices, faces = np.asarray(mesh.vertices, float), np.asarray(mesh.faces, np.int64)
    save_pieces(key, [vertices, faces.astype(float)])  # face indices are exact in float64
    return vertices, faces


def urdf_spec(path: str | Path, package_dirs=(), args: dict | None = None) -> tuple[mujoco.MjSpec, dict, list[str]]:
    """An MjSpec of a URDF/xacro with every mesh loaded and validated here; also the URDF's joint
    velocity limits by name and the moving links without <inertial> (`links_without_inertia`)."""
    path = Path(path).resolve()
    if not path.is_file():
        raise DesignError(f"robot: file '{path}' not found; check the path")
    roots = package_roots(package_dirs)
    roots.setdefault(path.parent.name, path.parent)
    root = with_inertials(path, roots, dict(args or {}), _urdf_root(path, roots, dict(args or {})))
    check_joints(root, str(path))
    guessed = links_without_inertia(root)
    meshes = []  # (link, kind, index, file, scale, pos, quat)
    for link in root.findall("link"):
        for kind in ("visual", "collision"):
            for k, el in enumerate(list(link.findall(kind))):
                m = el.find("geometry/mesh")
                if m is None:
                    continue
                where = f"robot file '{path.name}': link '{link.get('name')}' {kind} #{k}"
                file = resolve_uri(m.get("filename", ""), path.parent, roots, where)
                scale = [float(v) for v in m.get("scale", "1 1 1").split()]
                meshes.append((link.get("name"), kind, k, file, scale, *_origin(el), where))
                link.remove(el)
    vel = {j.get("name"): float(j.find("limit").get("velocity")) for j in root.findall("joint")
           if j.find("limit") is not None and j.find("limit").get("velocity")}
    mj = root.find("mujoco")
    mj = ET.SubElement(root, "mujoco") if mj is None else mj
    comp = mj.find("compiler")
    comp = ET.SubElement(mj, "compiler") if comp is None else comp
    comp.attrib.update(fusestatic="false", discardvisual="false", balanceinertia="true", strippath="false")
    try:
        spec = mujoco.MjSpec.from_string(ET.tostring(root, encoding="unicode"))
    except ValueError as e:
        raise DesignError(f"robot file '{path}': MuJoCo could not read the URDF: {e}") from None
    loaded: dict[tuple, object] = {}
    for link, kind, k, file, scale, pos, quat, where in meshes:
        key = (str(file), tuple(scale))
        if key not in loaded:
            vertices, faces = _checked_mesh(file, where, scale)
            name = f"{Path(file).stem}_{len(loaded)}"
            m = spec.add_mesh(name=name)
            m.uservert = vertices.ravel().tolist()
            m.userface = faces.ravel().tolist()
            loaded[key] = name
        body = spec.body(link)
        visual = kind == "visual"
        body.add_geom(name=f"{link}_{kind}_{k}", type=mujoco.mjtGeom.mjGEOM_MESH, meshname=loaded[key], pos=pos,
                      quat=quat, group=VISUAL_GROUP if visual else COLLISION_GROUP,
                      contype=0 if visual else 1, conaffinity=0 if visual else 1, density=0 if visual else 1000,
                      rgba=[0.85, 0.85, 0.88, 1] if visual else [0.5, 0.5, 0.6, 0.3])
    return spec, vel, guessed

"""Blender -> core: read the scene's robot, pose, link meshes, modules and stored design into
skinsafe.core objects (bulk reads through `foreach_get`)."""
import bpy
import numpy as np
from mathutils import Matrix

from skinsafe.core.design.surface import Surface
from skinsafe.core.robot.models import load_robot
from skinsafe.core.robot.urdf_import import parse_xacro_args
from skinsafe.core.skin import taxel_map
from skinsafe.core.skin.model import DesignError, Module, RobotRef

TEXT_NAME = "skinsafe_taxel_map.json"
COLLECTION = "skinsafe robot"  # the imported robot's body objects (and the modules on them)
_robots: dict = {}  # (kind, name, path) -> Robot
_designs: dict = {}  # scene name -> (design_rev, SkinDesign)
_surfaces: dict = {}  # object name -> (key, Surface)


def clear_caches() -> None:
    _robots.clear(), _designs.clear(), _surfaces.clear()


def robot_ref(scene) -> RobotRef | None:
    s = scene.skinsafe
    if not s.robot_kind:
        return None
    dirs = tuple(d for d in s.robot_package_dirs.split(";") if d)
    return RobotRef(s.robot_kind, s.robot_name, s.robot_path or None, dirs, parse_xacro_args(s.robot_xacro_args))


def preload(ref: RobotRef, fresh: bool = False):
    """Load the robot of `ref` (validated: joints, every mesh by link and file) into the cache `robot_for`
    reads; `fresh`: read its files again (an import: they may have changed). No bpy: it may run in a worker
    thread (addon/background.py)."""
    key = (ref.kind, ref.name, ref.path, ref.package_dirs, tuple(sorted(ref.xacro_args.items())))
    if fresh or key not in _robots:
        robot = load_robot(ref)  # a refusal leaves the cache as it was
        _robots[key] = robot
    return _robots[key]


def robot_for(scene):
    """The scene's robot (MuJoCo model and limits), loaded once per reference."""
    ref = robot_ref(scene)
    if ref is None:
        raise DesignError("scene: no robot imported; import one first (skinsafe panel > Robot)")
    return preload(ref)


def body_objects(scene) -> dict:
    """Body name -> Blender object of the scene's imported robot (`scene.skinsafe.links`; a file saved before
    the links were kept: the objects of the robot's collection, the one named as the body first)."""
    if len(scene.skinsafe.links):
        return {it.body: it.object for it in scene.skinsafe.links if it.object is not None}
    coll = bpy.data.collections.get(COLLECTION)
    out = {}
    for o in coll.objects if coll is not None else scene.objects:
        b = o.get("skinsafe_body")
        if b is not None and (b not in out or o.name == b):
            out[b] = o
    return out


def stray_bodies(scene) -> list[str]:
    """Names of the scene's objects that claim a robot body but are not the robot's (copies)."""
    mine = {o.name for o in body_objects(scene).values()}
    return sorted(o.name for o in scene.objects if "skinsafe_body" in o and o.name not in mine)


def pose(scene) -> np.ndarray:
    """qpos of the scene's pose: the robot's home, with every joint in the panel applied."""
    robot = robot_for(scene)
    m = robot.model
    q = robot.home.copy()
    for j in scene.skinsafe.joints:
        jid = m.joint(j.name).id
        q[m.jnt_qposadr[jid]] = j.value
    return q


def surface_of(obj) -> Surface:
    """The object's mesh (object frame = body frame) as a core Surface with its corner normals."""
    me = obj.data
    nv, nt = len(me.vertices), len(me.loop_triangles) if me.loop_triangles else 0
    if nt == 0:
        me.calc_loop_triangles()
        nt = len(me.loop_triangles)
    co = np.empty(nv * 3)
    me.vertices.foreach_get("co", co)
    key = (me.name, nv, nt, float(co.sum()))
    hit = _surfaces.get(obj.name)
    if hit and hit[0] == key:
        return hit[1]
    tri = np.empty(nt * 3, dtype=np.int64)
    me.loop_triangles.foreach_get("vertices", tri)
    loops = np.empty(nt * 3, dtype=np.int64)
    me.loop_triangles.foreach_get("loops", loops)
    cn = np.empty(len(me.loops) * 3)
    me.corner_normals.foreach_get("vector", cn)
    surf = Surface.from_mesh(co.reshape(-1, 3), tri.reshape(-1, 3), cn.reshape(-1, 3)[loops].reshape(-1, 3, 3),
                             name=obj["skinsafe_body"])
    _surfaces[obj.name] = (key, surf)
    return surf


def module_objects(scene) -> list:
    return [o for o in scene.objects if o.skinsafe_module.is_module]


def settings_module(settings, module_id: int, name: str, body: str) -> Module:
    """The core Module described by template settings (a module object's or the scene's)."""
    s = settings
    return Module(id=int(module_id), name=name, body=body, template=s.template, rows=s.rows, cols=s.cols,
                  pitch=s.pitch, taxel_diameter=s.taxel_diameter, margin=s.margin, min_bend_radius=s.min_bend_radius,
                  max_strain=s.max_strain)


def outline_of(settings) -> np.ndarray | None:
    """A curve object's points (its local x, y in m) as the 'curve' template's outline (x negated for a
    mirrored module)."""
    cu = settings.outline
    if settings.template != "curve" or cu is None or cu.type != "CURVE":
        return None
    pts = []
    for sp in cu.data.splines:
        seq = sp.bezier_points if sp.type == "BEZIER" else sp.points
        pts += [tuple(p.co[:2]) for p in seq]
    return np.asarray(pts, dtype=float) * np.asarray(cu.scale[:2]) * ((-1.0 if settings.mirrored else 1.0), 1.0)


def placement_of(obj) -> tuple[np.ndarray, np.ndarray]:
    """Anchor and row direction of a module object in its body's frame (its local matrix)."""
    M = np.array(obj.matrix_basis)  # parent inverse is identity: basis = local = body frame
    return M[:3, 3].copy(), M[:3, 0] / max(np.linalg.norm(M[:3, 0]), 1e-12)


def matrix_key(obj) -> list[float]:
    return [c for row in obj.matrix_basis for c in row]


def mesh_key(me, samples: int = 32) -> tuple[float, ...]:
    """A mesh's vertex count, first vertex and a weighted sum of `samples` of its vertices spread over it: any
    transform, origin or modifier applied changes it, and reading it costs the same on a 50,000-vertex link."""
    n = len(me.vertices)
    co = np.array([me.vertices[int(i)].co for i in np.linspace(0, n - 1, min(n, samples))]).reshape(-1)
    first = co[:3] if len(co) else np.zeros(3)
    return (float(n), *map(float, first), float(co @ (1.0 + np.arange(len(co)) % 7)))


def close(a, b, atol: float) -> bool:
    """Whether two sequences of numbers agree within `atol` (np.allclose's work without its overhead: it runs for
    every object in every update)."""
    return float(np.max(np.abs(np.subtract(a, b)), initial=0.0)) <= atol


def moved(obj) -> bool:
    """Whether a module object's transform changed since it was last placed."""
    return not close(matrix_key(obj), obj.skinsafe_module.placed_matrix, 1e-7)


def design_of(scene):
    """The scene's skin design (from the cache, or parsed from the .blend's taxel-map text)."""
    rev = scene.skinsafe.design_rev
    hit = _designs.get(scene.name)
    if hit and hit[0] == rev:
        return hit[1]
    text = bpy.data.texts.get(TEXT_NAME)
    if text is None or not text.as_string().strip():
        return None
    import json
    design = taxel_map.from_dict(json.loads(text.as_string()), f"text '{TEXT_NAME}'")
    _designs[scene.name] = (rev, design)
    return design


def world_matrix(obj) -> np.ndarray:
    return np.array(obj.matrix_world)


def to_matrix(a) -> Matrix:
    return Matrix([list(r) for r in np.asarray(a)])

"""Shared by the headless add-on scripts (tests/addon_headless*.py, run by
tests/addon/test_addon.py with the pip bpy module): the test scene, installing the
built zip, and snapshots of RNA data to compare before / after."""
import time

import bpy

MODULE = "bl_ext.user_default.dcdi_lens_bokeh"


def install(zip_path):
    """Install and enable the extension zip in the user repository: (result, seconds)."""
    t = time.perf_counter()
    result = sorted(bpy.ops.extensions.package_install_files(filepath=str(zip_path), repo="user_default",
                                                             enable_on_install=True))
    return result, time.perf_counter() - t


def error_of(fn):
    """The message of the RuntimeError an operator call raises (an ERROR
    report or a failed poll), or None when it ran."""
    try:
        fn()
    except RuntimeError as e:
        return str(e)
    return None


class StubLayout:
    """Records what a panel's draw() asks for (pip bpy has no UI to draw into)."""

    def __init__(self, log=None):
        self.log = [] if log is None else log

    def _child(self, *a, **k):
        return StubLayout(self.log)

    row = column = box = split = _child

    def label(self, text="", **k):
        self.log.append(("label", text, k.get("icon")))

    def operator(self, idname, **k):
        self.log.append(("operator", idname, k.get("icon")))
        return StubLayout(self.log)

    def prop(self, data, name, **k):
        self.log.append(("prop", name, None))

    def template_icon(self, icon_value=0, **k):
        self.log.append(("icon", icon_value, None))


def snapshot(struct, depth=0, max_depth=4):
    """Every RNA property of ``struct`` (nested structs to max_depth; ID
    pointers by name), as plain Python values, to compare before / after."""
    out = {}
    for prop in struct.bl_rna.properties:
        k = prop.identifier
        if k in ("rna_type", "depsgraph"):       # the depsgraph is transient evaluation state
            continue
        try:
            v = getattr(struct, k)
        except (AttributeError, RuntimeError, ReferenceError):
            continue
        if prop.type == "POINTER":
            if v is None or isinstance(v, bpy.types.ID):
                out[k] = None if v is None else ("ID", v.name)
            elif depth < max_depth:
                out[k] = snapshot(v, depth + 1, max_depth)
        elif prop.type == "COLLECTION":
            items = list(v)
            if items and isinstance(items[0], bpy.types.ID):
                out[k] = [("ID", x.name) for x in items]
            elif depth < max_depth:
                out[k] = [snapshot(x, depth + 1, max_depth) for x in items]
        else:
            try:
                out[k] = tuple(v) if hasattr(v, "__len__") and not isinstance(v, str) else v
            except TypeError:
                out[k] = repr(v)
    return out


def diff(a, b, path=""):
    if isinstance(a, dict) and isinstance(b, dict):
        return [d for k in sorted(set(a) | set(b)) for d in diff(a.get(k), b.get(k), f"{path}.{k}")]
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        return [d for i, (x, y) in enumerate(zip(a, b)) for d in diff(x, y, f"{path}[{i}]")]
    return [] if a == b else [f"{path}: {a!r} -> {b!r}"]


def data_counts():
    # (Blender 5.2's all_ids lists every ID again: a new image would count twice)
    return {k: len(getattr(bpy.data, k)) for k in dir(bpy.data)
            if k != "all_ids" and isinstance(getattr(bpy.data, k, None), bpy.types.bpy_prop_collection)}


def emission_checker(name, scale):
    """An emission material with a checker texture: sharp edges at every
    depth, no lights needed, little render noise."""
    mat = bpy.data.materials.new(name)
    mat.use_nodes = True
    nt = mat.node_tree
    nt.nodes.clear()
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    em = nt.nodes.new("ShaderNodeEmission")
    chk = nt.nodes.new("ShaderNodeTexChecker")
    chk.inputs["Scale"].default_value = scale
    chk.inputs["Color1"].default_value = (0.9, 0.8, 0.7, 1.0)
    chk.inputs["Color2"].default_value = (0.05, 0.1, 0.2, 1.0)
    nt.links.new(chk.outputs["Color"], em.inputs["Color"])
    nt.links.new(em.outputs["Emission"], out.inputs["Surface"])
    return mat


def build_scene():
    """Camera at the origin looking down -Z; a checker cube 0.85-1.15 m away,
    a checker wall 8 m away; 640 x 480 render (preview 128 x 96)."""
    for ob in list(bpy.data.objects):
        bpy.data.objects.remove(ob)
    scene = bpy.context.scene
    cam = bpy.data.objects.new("Cam", bpy.data.cameras.new("Cam"))
    scene.collection.objects.link(cam)
    scene.camera = cam
    bpy.ops.mesh.primitive_plane_add(size=40.0, location=(0.0, 0.0, -8.0))
    bpy.context.object.data.materials.append(emission_checker("wall", 80.0))
    bpy.ops.mesh.primitive_cube_add(size=0.3, location=(0.0, 0.0, -1.0))
    cube = bpy.context.object
    cube.data.materials.append(emission_checker("cube", 6.0))
    scene.world = bpy.data.worlds.new("black")
    scene.render.resolution_x, scene.render.resolution_y = 640, 480
    return scene, cam, cube


def settle(preview, limit_s=120.0):
    """Step the viewport preview's refresh (``preview.tick``) until it has
    nothing left to do (the debounce waited out)."""
    import time
    t = time.perf_counter()
    while True:
        nxt = preview.tick()
        if nxt is None:
            return
        if time.perf_counter() - t > limit_s:
            raise RuntimeError("the preview did not settle")
        time.sleep(min(nxt, 0.05))

"""The viewport preview's sharp image and planar Z drawn on the GPU (a
Blender with a window), measured against Cycles by ui_preview.py: the
design that was tried for the preview and left out of it (docs/addon.md,
Preview in Viewport: what the GPU can give).

- the planar Z: every visible evaluated mesh (``object_instances`` of the
  view layer's depsgraph) drawn through the camera's view and projection
  with a small shader that writes camera-space -z (planar Z in scene units,
  what Cycles's Z pass holds) into an R32F colour target, a depth texture
  for the depth test; where nothing is drawn, 1e10 (as Cycles writes for
  the world). Each object's batch (its evaluated mesh's triangles, in
  object space) is kept by its name and rebuilt when its geometry changed
  (:meth:`GPUCapture.geometry_changed`) or its data differs;
- the colour: ``GPUOffScreen.draw_view3d`` of the 3D view that shows the
  camera, through the camera's matrices at the preview size, in that
  view's shading, overlays off, linear (no colour management).
"""
from __future__ import annotations

import time

import bpy
import numpy as np

BACKGROUND_Z = 1e10            # Cycles's Z where a ray hits nothing
# object types whose evaluated geometry is a mesh (to_mesh)
GEOMETRY_TYPES = frozenset(("MESH", "CURVE", "SURFACE", "META", "FONT"))

_VERTEX = """
void main()
{
  vec4 v = u_modelview * vec4(pos, 1.0);
  zcam = -v.z;
  gl_Position = u_projection * v;
}
"""
_FRAGMENT = """
void main()
{
  out_z = vec4(zcam, 0.0, 0.0, 1.0);
}
"""


def available() -> bool:
    """Whether this Blender draws on a GPU (a window; not ``-b`` nor pip bpy)."""
    if bpy.app.background:
        return False
    try:
        import gpu  # noqa: F401
    except ImportError:
        return False
    return True


def draws_materials(space, scene) -> bool:
    """Whether the 3D view ``space`` shows the objects' materials: Material
    Preview, or Rendered with an engine that draws on the GPU (EEVEE,
    Workbench). Solid shows each object's viewport colour (by default the
    same grey for all, textures and shading nodes left out: nothing like the
    render); Rendered with Cycles would run Cycles in the offscreen drawing."""
    shading = space.shading.type
    return shading == "MATERIAL" or (shading == "RENDERED" and scene.render.engine != "CYCLES")


def compiling() -> bool:
    """Whether Blender is compiling shaders (the viewport's materials) in the background."""
    try:
        return bool(bpy.app.is_job_running("SHADER_COMPILATION"))
    except (TypeError, ValueError, AttributeError):
        return False


def camera_view(context):
    """(area, space, region) of the 3D view that looks through the camera
    (the largest), else of the largest 3D view; None without one."""
    best = None
    wm = getattr(context, "window_manager", None)
    for window in (wm.windows if wm else ()):
        for area in window.screen.areas:
            if area.type != "VIEW_3D":
                continue
            space = area.spaces.active
            region = next((r for r in area.regions if r.type == "WINDOW"), None)
            if region is None or space.region_3d is None:
                continue
            rank = (space.region_3d.view_perspective == "CAMERA", area.width * area.height)
            if best is None or rank > best[0]:
                best = (rank, (area, space, region))
    return None if best is None else best[1]


def camera_matrices(camera, depsgraph, h: int, w: int):
    """(view, projection) of ``camera`` (evaluated) at w x h pixels (mathutils matrices)."""
    cam = camera.evaluated_get(depsgraph)
    view = cam.matrix_world.normalized().inverted()
    projection = cam.calc_matrix_camera(depsgraph, x=w, y=h)
    return view, projection


class GPUCapture:
    """The shader, the targets and each object's batch, kept between captures."""

    def __init__(self):
        self.shader = None
        self.batches: dict = {}         # object name -> (key, batch)
        self.changed: set = set()       # names whose geometry changed since their batch was made
        self.generation = 0             # bumped by geometry_changed(None): every batch is stale
        self.targets = None             # (h, w, framebuffer, z texture, depth texture)
        self.offscreen = None           # (h, w, GPUOffScreen)
        self.log: dict = {}

    # ------------------------------------------------------------ changes
    def geometry_changed(self, name: str | None) -> None:
        """Object ``name``'s geometry changed (None: maybe every object's: a new frame)."""
        if name is None:
            self.generation += 1
        else:
            self.changed.add(name)

    def free(self) -> None:
        self.batches.clear()
        self.changed.clear()
        self.targets = None
        if self.offscreen is not None:
            self.offscreen[2].free()
        self.offscreen = None

    # ------------------------------------------------------------ depth
    def _shader(self):
        if self.shader is None:
            import gpu
            info = gpu.types.GPUShaderCreateInfo()
            info.push_constant("MAT4", "u_modelview")
            info.push_constant("MAT4", "u_projection")
            info.vertex_in(0, "VEC3", "pos")
            iface = gpu.types.GPUStageInterfaceInfo("dcdi_planar_z_iface")
            iface.smooth("FLOAT", "zcam")
            info.vertex_out(iface)
            info.fragment_out(0, "VEC4", "out_z")
            info.vertex_source(_VERTEX)
            info.fragment_source(_FRAGMENT)
            self.shader = gpu.shader.create_from_info(info)
        return self.shader

    def _batch(self, obj, eval_obj):
        """The batch of ``eval_obj``'s evaluated mesh (object space), kept by
        ``obj``'s name; None when it has no triangles."""
        from gpu_extras.batch import batch_for_shader
        name = obj.name
        kept = self.batches.get(name)
        data = getattr(eval_obj, "data", None)
        key = (getattr(data, "name", None), self.generation)
        if kept is not None and kept[0] == key and name not in self.changed:
            return kept[1]
        mesh = eval_obj.to_mesh()
        try:
            n_v, n_t = len(mesh.vertices), len(mesh.loop_triangles)
            if n_t == 0:
                batch = None
            else:
                co = np.empty(n_v * 3, np.float32)
                mesh.vertices.foreach_get("co", co)
                tris = np.empty(n_t * 3, np.int32)
                mesh.loop_triangles.foreach_get("vertices", tris)
                batch = batch_for_shader(self._shader(), "TRIS", {"pos": co.reshape(-1, 3)},
                                         indices=tris.reshape(-1, 3))
        finally:
            eval_obj.to_mesh_clear()
        self.batches[name] = (key, batch)
        self.changed.discard(name)
        return batch

    def _targets(self, h: int, w: int):
        import gpu
        if self.targets is None or self.targets[:2] != (h, w):
            z = gpu.types.GPUTexture((w, h), format="R32F")
            depth = gpu.types.GPUTexture((w, h), format="DEPTH_COMPONENT32F")
            fb = gpu.types.GPUFrameBuffer(depth_slot=depth, color_slots=z)
            self.targets = (h, w, fb, z, depth)
        return self.targets[2]

    def planar_z(self, depsgraph, view, projection, h: int, w: int) -> np.ndarray:
        """(h, w) float32 camera-space -z of the nearest surface, scene units; BACKGROUND_Z where none."""
        import gpu
        shader = self._shader()
        drawn = []
        seen = set()
        for inst in depsgraph.object_instances:
            eval_obj = inst.object                   # for an instance: the instanced object, evaluated
            if eval_obj.type not in GEOMETRY_TYPES:
                continue
            if not inst.is_instance and not eval_obj.original.visible_get():
                continue
            batch = self._batch(eval_obj.original, eval_obj)
            seen.add(eval_obj.original.name)
            if batch is not None:
                drawn.append((view @ inst.matrix_world, batch))
        for name in [n for n in self.batches if n not in seen]:
            del self.batches[name]
        fb = self._targets(h, w)
        with fb.bind():
            fb.clear(color=(BACKGROUND_Z, 0.0, 0.0, 0.0), depth=1.0)
            gpu.state.depth_test_set("LESS_EQUAL")
            gpu.state.depth_mask_set(True)
            gpu.state.blend_set("NONE")
            gpu.state.face_culling_set("NONE")
            shader.bind()
            shader.uniform_float("u_projection", projection)
            for modelview, batch in drawn:
                shader.uniform_float("u_modelview", modelview)
                batch.draw(shader)
            gpu.state.depth_test_set("NONE")
            gpu.state.depth_mask_set(False)
            buf = fb.read_color(0, 0, w, h, 1, 0, "FLOAT")
        z = np.asarray(buf, np.float32).reshape(h, w)[::-1].copy()
        return z

    # ------------------------------------------------------------ colour
    def colour(self, context, scene, view_layer, view, projection, h: int, w: int, where=None) -> np.ndarray:
        """(h, w, 3) float32 linear colour of the 3D view ``where`` (area,
        space, region; :func:`camera_view`) drawn through the camera."""
        import gpu
        where = where or camera_view(context)
        if where is None:
            raise RuntimeError("no 3D view to draw the preview's colour with")
        _, space, region = where
        if self.offscreen is None or self.offscreen[:2] != (h, w):
            if self.offscreen is not None:
                self.offscreen[2].free()
            self.offscreen = (h, w, gpu.types.GPUOffScreen(w, h, format="RGBA16F"))
        off = self.offscreen[2]
        overlay = space.overlay
        shown = overlay.show_overlays
        if shown:
            overlay.show_overlays = False           # the selection's outline, origins, the grid: not the scene
        try:
            off.draw_view3d(scene, view_layer, space, region, view, projection, do_color_management=False)
        finally:
            if shown:
                overlay.show_overlays = True
        buf = off.texture_color.read()
        rgba = np.asarray(buf, np.float32).reshape(h, w, 4)
        return rgba[::-1, :, :3].copy()

    # ------------------------------------------------------------ both
    def capture(self, context, scene, camera, h: int, w: int, *, colour: bool = True, where=None):
        """(rgb or None, planar z, seconds {colour, depth}) of ``camera`` at
        h x w; the colour drawn by the 3D view ``where`` (:func:`camera_view`)."""
        depsgraph = context.evaluated_depsgraph_get()
        view, projection = camera_matrices(camera, depsgraph, h, w)
        t0 = time.perf_counter()
        z = self.planar_z(depsgraph, view, projection, h, w)
        t1 = time.perf_counter()
        rgb = self.colour(context, scene, context.view_layer, view, projection, h, w, where) if colour else None
        t2 = time.perf_counter()
        self.log = {"depth_s": t1 - t0, "colour_s": t2 - t1}
        return rgb, z, self.log

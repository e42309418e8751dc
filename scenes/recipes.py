"""Scene recipes: each builds a seeded procedural scene in the current bpy scene.

The camera sits at the origin looking along -Z (Blender's default camera
orientation), so an object's depth is its -z in metres. Recipes spread
objects over depth so that the depth histogram covers 0.7 m to beyond 10 m,
with procedural textures (no downloads) and lights.
"""
from __future__ import annotations

import math



def _bpy():
    import bpy
    return bpy


def material(name: str, rng, kind: str = "noise", scale: float | None = None):
    """A Principled BSDF whose base colour is a procedural texture through a
    two-colour ramp (colours drawn from ``rng``)."""
    bpy = _bpy()
    mat = bpy.data.materials.new(name)
    nt = mat.node_tree
    bsdf = next(n for n in nt.nodes if n.bl_idname == "ShaderNodeBsdfPrincipled")
    tex_type = {"noise": "ShaderNodeTexNoise", "voronoi": "ShaderNodeTexVoronoi",
                "checker": "ShaderNodeTexChecker", "wave": "ShaderNodeTexWave"}[kind]
    tex = nt.nodes.new(tex_type)
    tex.inputs["Scale"].default_value = float(scale if scale is not None else rng.uniform(3.0, 40.0))
    ramp = nt.nodes.new("ShaderNodeValToRGB")
    c0, c1 = rng.uniform(0.02, 0.9, 3), rng.uniform(0.02, 0.9, 3)
    ramp.color_ramp.elements[0].color = (*c0, 1.0)
    ramp.color_ramp.elements[1].color = (*c1, 1.0)
    out = tex.outputs["Fac"] if "Fac" in tex.outputs else tex.outputs[0]
    if kind == "voronoi":
        out = tex.outputs["Distance"]
    nt.links.new(out, ramp.inputs["Fac"])
    nt.links.new(ramp.outputs["Color"], bsdf.inputs["Base Color"])
    bsdf.inputs["Roughness"].default_value = float(rng.uniform(0.3, 0.9))
    return mat


def add_mesh(kind: str, location, scale, mat, rotation=(0.0, 0.0, 0.0)):
    bpy = _bpy()
    ops = {"cube": bpy.ops.mesh.primitive_cube_add, "sphere": bpy.ops.mesh.primitive_uv_sphere_add,
           "plane": bpy.ops.mesh.primitive_plane_add, "cylinder": bpy.ops.mesh.primitive_cylinder_add}
    ops[kind](location=tuple(float(v) for v in location), rotation=tuple(float(v) for v in rotation))
    obj = bpy.context.active_object
    obj.scale = tuple(float(v) for v in scale)
    obj.data.materials.append(mat)
    return obj


def add_light(kind: str, location, energy: float, rotation=(0.0, 0.0, 0.0), size: float = 1.0):
    bpy = _bpy()
    light = bpy.data.lights.new(f"{kind.lower()}-light", kind)
    light.energy = float(energy)
    if kind == "AREA":
        light.size = float(size)
    obj = bpy.data.objects.new(light.name, light)
    obj.location = tuple(float(v) for v in location)
    obj.rotation_euler = tuple(float(v) for v in rotation)
    bpy.context.scene.collection.objects.link(obj)
    return obj


def world(colour, strength: float = 1.0):
    bpy = _bpy()
    w = bpy.data.worlds.new("world")
    bg = next(n for n in w.node_tree.nodes if n.bl_idname == "ShaderNodeBackground")
    bg.inputs["Color"].default_value = (*colour, 1.0)
    bg.inputs["Strength"].default_value = float(strength)
    bpy.context.scene.world = w


def room(rng) -> None:
    """Indoor, the camera 1.2 m above the floor: back wall at 6-9 m, side
    walls, ceiling; one or two foreground pieces (lamp pole, shelf edge) at
    0.7-1.3 m off centre, a sideboard or two with small things on top at
    1.2-3.5 m, furniture-scale boxes and spheres on the floor at 2.5-5 m; a
    ceiling area light. (Measured depth bands: python -m
    blender_addon.tools.depth_histogram; at a 46 degree vertical field the floor
    only enters the frame beyond 2.9 m, so near content must stand tall.)"""
    floor = -1.2
    back = rng.uniform(6.0, 9.0)
    add_mesh("plane", (0, floor, -back / 2), (3.2, back / 2 + 0.5, 1), material("floor", rng, "checker", 8.0),
             rotation=(-math.pi / 2, 0, 0))
    add_mesh("plane", (0, 1.4, -back / 2), (3.2, back / 2 + 0.5, 1), material("ceiling", rng, "noise", 4.0),
             rotation=(math.pi / 2, 0, 0))
    add_mesh("plane", (0, 0.1, -back), (3.2, 1.3, 1), material("wall", rng, "noise"))
    for side in (-1, 1):
        add_mesh("plane", (side * 3.2, 0.1, -back / 2), (back / 2 + 0.5, 1.3, 1), material("side", rng, "wave"),
                 rotation=(0, side * math.pi / 2, 0))
    for i in range(int(rng.integers(1, 3))):
        # foreground: tall and thin, standing on the floor, reaching into the frame's side
        z = -rng.uniform(0.7, 1.3)
        x = float(rng.choice([-1.0, 1.0])) * rng.uniform(0.2, 0.5) * -z
        s = rng.uniform(0.025, 0.07)
        top = rng.uniform(0.2, 1.4)
        half_h = (top - floor) / 2
        mat = material(f"near{i}", rng, str(rng.choice(["noise", "wave", "voronoi"])))
        if rng.random() < 0.5:          # a pole: the cylinder's axis (local z) turned upright
            add_mesh("cylinder", (x, floor + half_h, z - s), (s, s, half_h), mat, rotation=(math.pi / 2, 0, 0))
        else:                           # a shelf's edge
            add_mesh("cube", (x, floor + half_h, z - s), (s, half_h, s), mat)
    for j in range(int(rng.integers(1, 3))):
        # a sideboard (top 0.75 m above the floor) and small things on it
        z = -rng.uniform(1.2, 2.8)
        x = rng.uniform(-0.5, 0.5) * -z
        half = (rng.uniform(0.35, 0.7), 0.375, rng.uniform(0.25, 0.45))
        add_mesh("cube", (x, floor + half[1], z), half, material(f"board{j}", rng, "wave"))
        for i in range(int(rng.integers(2, 5))):
            s = rng.uniform(0.04, 0.12)
            add_mesh(str(rng.choice(["cube", "sphere", "cylinder"])),
                     (x + rng.uniform(-0.8, 0.8) * half[0], floor + 0.75 + s, z + rng.uniform(-0.6, 0.6) * half[2]),
                     (s, s, s), material(f"small{j}-{i}", rng, str(rng.choice(["noise", "voronoi", "checker"]))))
    for i in range(int(rng.integers(3, 6))):
        z = -rng.uniform(2.5, 5.0)
        x = rng.uniform(-1.0, 1.0) * 0.45 * -z
        kind = "cube" if rng.random() < 0.6 else "sphere"
        s = rng.uniform(0.2, 0.5)
        add_mesh(kind, (x, floor + s, z), (s, s * rng.uniform(0.6, 2.0), s),
                 material(f"thing{i}", rng, str(rng.choice(["noise", "voronoi", "checker"]))))
    add_light("AREA", (0, 1.35, -back / 2), 120.0 * (back / 6.0) ** 2, rotation=(0, 0, 0), size=3.0)
    add_light("SUN", (2, 4, 2), 1.5, rotation=(0.6, 0.2, 0.3))
    world((0.05, 0.05, 0.06), 0.5)


def tabletop(rng) -> None:
    """Close-up: a table top from 0.3 m to 2.3 m (in the frame beyond 0.83 m),
    small objects with front faces at 0.72-1.5 m, a wall behind at 2.5-3.5 m."""
    add_mesh("plane", (0, -0.35, -1.3), (1.2, 1.0, 1), material("table", rng, "wave", 6.0),
             rotation=(-math.pi / 2, 0, 0))
    add_mesh("plane", (0, 0.5, -rng.uniform(2.5, 3.5)), (3.0, 2.0, 1), material("wall", rng, "noise"))
    for i in range(int(rng.integers(5, 9))):
        # objects' front faces at >= 0.72 m: below the PSF library's 0.7 m the simulation clamps
        s = rng.uniform(0.04, 0.12)
        z = -rng.uniform(0.72, 1.5) - s
        add_mesh(str(rng.choice(["cube", "sphere", "cylinder"])), (rng.uniform(-0.35, 0.35) * -z, -0.35 + s, z),
                 (s, s, s), material(f"obj{i}", rng, str(rng.choice(["noise", "voronoi", "checker"]))))
    add_light("AREA", (0.3, 1.0, -0.5), 20.0, rotation=(-1.2, 0, 0), size=1.0)
    world((0.6, 0.6, 0.65), 0.3)


def street(rng) -> None:
    """Outdoor: a ground plane to 80 m, buildings (boxes) at 6-40 m, trees
    (cylinder + sphere) at 3-25 m, sky (infinitely far) above."""
    add_mesh("plane", (0, -1.6, -40), (40, 42, 1), material("road", rng, "noise", 20.0),
             rotation=(-math.pi / 2, 0, 0))
    for i in range(int(rng.integers(6, 12))):
        z = -rng.uniform(6.0, 40.0)
        side = rng.choice([-1.0, 1.0])
        h = rng.uniform(3.0, 12.0)
        add_mesh("cube", (side * rng.uniform(4.0, 12.0), -1.6 + h / 2, z), (rng.uniform(1.5, 4.0), h / 2, rng.uniform(1.5, 4.0)),
                 material(f"building{i}", rng, "checker", float(rng.uniform(4, 12))))
    for i in range(int(rng.integers(3, 7))):
        z = -rng.uniform(3.0, 25.0)
        x = rng.uniform(-3.0, 3.0)
        add_mesh("cylinder", (x, -0.8, z), (0.15, 0.15, 0.8), material(f"trunk{i}", rng, "wave"),
                 rotation=(math.pi / 2, 0, 0))
        add_mesh("sphere", (x, 0.6, z), (1.0, 1.0, 1.0), material(f"crown{i}", rng, "voronoi"))
    add_light("SUN", (0, 10, 0), 3.0, rotation=(0.9, 0.1, 0.4))
    world((0.45, 0.6, 0.9), 1.0)


def plane_at(rng, distance_m: float = 2.5) -> None:
    """A fronto-parallel textured plane at ``distance_m`` (for checks)."""
    add_mesh("plane", (0, 0, -distance_m), (50, 50, 1), material("plane", rng, "checker", 30.0))
    add_light("SUN", (0, 0, 5), 2.0)
    world((0.0, 0.0, 0.0), 0.0)


RECIPES = {"room": room, "tabletop": tabletop, "street": street, "plane": plane_at}

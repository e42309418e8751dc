"""Scene recipes: each builds a seeded scene in the current bpy scene.

The camera sits at the origin looking along -Z with +Y up (Blender's
default camera orientation), so an object's planar depth is its -z in
metres. The indoor recipes fill a room or a table with 20-60 objects of
every size at 0.7-5 m that occlude each other (depth edges everywhere);
the street puts its clutter at 3-40 m before a sky. Every surface gets a
procedural material with detail at every scale, or an image from the
user's texture folder (scenes/materials.py). ``leaves`` is not a Blender
scene: the factory draws it in numpy (dcdi_core/dataset/leaves.py).

Measured depth mix and texture per recipe: ``dcdi dataset stats`` on a
factory folder (docs/factory.md).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

# objects a recipe places, the room's walls, floor and ceiling not counted
MAX_OBJECTS = 60
# materials drawn per size class (a factor of two in size) before objects share them
MATERIALS_PER_SIZE = 4


def _bpy():
    import bpy
    return bpy


# ------------------------------------------------------------------ building blocks
_BASE_MESHES: dict[str, object] = {}


def _base_mesh(kind: str):
    """One unit mesh per primitive kind (cube of half-size 1, sphere and
    cylinder of radius 1, the cylinder and cone along local z from -1 to 1,
    a plane of half-size 1 in local xy), made once per scene by Blender's
    primitive operator and copied per object: much faster than an operator
    call per object. (Meshes built with bmesh instead rendered with
    last-bit differences from one render of the same scene to the next.)"""
    bpy = _bpy()
    me = _BASE_MESHES.get(kind)
    if me is not None:
        return me
    # flat shading, finely divided: Blender's smooth normals (averaged, or set per vertex) came out
    # with last-bit differences from one render of the same scene to the next
    ops = {"cube": bpy.ops.mesh.primitive_cube_add,
           "sphere": lambda: bpy.ops.mesh.primitive_uv_sphere_add(segments=64, ring_count=32),
           "cylinder": lambda: bpy.ops.mesh.primitive_cylinder_add(vertices=64),
           "cone": lambda: bpy.ops.mesh.primitive_cone_add(vertices=64),
           "plane": bpy.ops.mesh.primitive_plane_add}
    ops[kind]()
    obj = bpy.context.active_object
    me = obj.data
    me.name = f"unit-{kind}"
    bpy.data.objects.remove(obj)
    _BASE_MESHES[kind] = me
    return me


UPRIGHT = (math.pi / 2, 0.0, 0.0)       # turns a cylinder's or cone's local z axis to +Y (up)


@dataclass
class Builder:
    """Places objects in the current bpy scene and gives each a material.
    ``records`` collects what each surface got (the factory writes them to
    the manifest); ``objects`` counts what was placed besides the shell."""
    rng: np.random.Generator
    textures: object = None                 # a dcdi_core.dataset.textures.TextureLibrary, or None
    records: list = field(default_factory=list)
    objects: int = 0
    pool: dict = field(default_factory=dict)    # size class -> [(material, record)] shared by objects

    def full(self, n: int = 1) -> bool:
        """Would ``n`` more objects pass MAX_OBJECTS?"""
        return self.objects + n > MAX_OBJECTS

    def material(self, name: str, size_m: float, kind: str | None = None, prefer: tuple = ()):
        """A material for a surface ``size_m`` metres across: of ``kind``, or
        one of ``prefer`` (a facade: bricks, tiles, plaster) unless the
        user's textures win the draw, or any kind."""
        from scenes.materials import surface_material
        if kind is None and prefer:
            use_image = self.textures is not None and self.rng.random() < 0.5
            kind = "image" if use_image else str(self.rng.choice(prefer))
        if kind is None:
            # objects of one size class share up to MATERIALS_PER_SIZE materials: building a material's
            # nodes costs ~15 ms, and the patterns lie in world metres, so two objects sharing one still
            # show different texture
            shared = self.pool.setdefault(round(math.log2(size_m)), [])
            if len(shared) >= MATERIALS_PER_SIZE:
                mat, record = shared[int(self.rng.integers(len(shared)))]
                self.records.append({"surface": name, **record})
                return mat
        mat, record = surface_material(name, self.rng, kind=kind, textures=self.textures, size_m=size_m)
        if kind is None:
            shared.append((mat, record))
        self.records.append({"surface": name, **record})
        return mat

    def add(self, kind: str, name: str, location, scale, rotation=(0.0, 0.0, 0.0), *, mat=None,
            material_kind: str | None = None, prefer: tuple = (), shell: bool = False):
        """A primitive (see _base_mesh) at ``location`` (m), scaled by
        ``scale`` (its half-sizes, m), rotated (XYZ Euler, radians)."""
        if not shell and self.full():
            return None                 # the budget is spent: compound things check before they start
        bpy = _bpy()
        me = _base_mesh(kind).copy()
        me.name = name
        if mat is None:
            mat = self.material(name, 2.0 * float(max(scale)), material_kind, prefer)
        me.materials.append(mat)
        obj = bpy.data.objects.new(name, me)
        obj.location = tuple(float(v) for v in location)
        obj.scale = tuple(float(v) for v in scale)
        obj.rotation_euler = tuple(float(v) for v in rotation)
        bpy.context.scene.collection.objects.link(obj)
        if not shell:
            self.objects += 1
        return obj

    def box(self, name, centre, half, **kw):
        return self.add("cube", name, centre, half, **kw)

    def upright(self, kind, name, base, radius, height, **kw):
        """A cylinder or cone standing on ``base`` (x, y, z), ``height`` m tall."""
        x, y, z = base
        return self.add(kind, name, (x, y + height / 2, z), (radius, radius, height / 2), UPRIGHT, **kw)


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


def world(colour, strength: float = 1.0, clouds_rng=None):
    """The background at infinity: a plain colour, or with ``clouds_rng`` a
    sky of multi-octave clouds (noise over the view direction, features
    from a tenth of the sky down to below a pixel's angle)."""
    bpy = _bpy()
    w = bpy.data.worlds.new("world")
    nt = w.node_tree
    bg = next(n for n in nt.nodes if n.bl_idname == "ShaderNodeBackground")
    bg.inputs["Color"].default_value = (*colour, 1.0)
    bg.inputs["Strength"].default_value = float(strength)
    if clouds_rng is not None:
        coords = nt.nodes.new("ShaderNodeTexCoord")
        noise = nt.nodes.new("ShaderNodeTexNoise")
        noise.inputs["Scale"].default_value = float(clouds_rng.uniform(3.0, 8.0))
        noise.inputs["Detail"].default_value = 7.0        # 2^7 finer than the clouds: below a pixel's angle
        noise.inputs["Roughness"].default_value = float(clouds_rng.uniform(0.55, 0.7))
        ramp = nt.nodes.new("ShaderNodeValToRGB")
        ramp.color_ramp.elements[0].position = float(clouds_rng.uniform(0.35, 0.5))
        ramp.color_ramp.elements[0].color = (*colour, 1.0)
        ramp.color_ramp.elements[1].position = float(clouds_rng.uniform(0.6, 0.8))
        ramp.color_ramp.elements[1].color = (*(np.full(3, clouds_rng.uniform(0.7, 0.95))), 1.0)
        nt.links.new(coords.outputs["Generated"], noise.inputs["Vector"])
        nt.links.new(noise.outputs["Fac"], ramp.inputs["Fac"])
        # only camera rays see the clouds: light that bounces (and the world's importance map) sees the
        # plain sky, which kept the render time (clouds for every ray: twice the street's render)
        path = nt.nodes.new("ShaderNodeLightPath")
        mix = nt.nodes.new("ShaderNodeMix")
        mix.data_type = "RGBA"
        mix.inputs["A"].default_value = (*colour, 1.0)
        nt.links.new(path.outputs["Is Camera Ray"], mix.inputs["Factor"])
        nt.links.new(ramp.outputs["Color"], mix.inputs["B"])
        nt.links.new(mix.outputs["Result"], bg.inputs["Color"])
        # the light the sky sheds is the plain colour: a coarse importance map suffices (the default map,
        # 1024 px, is built by evaluating the clouds' nodes and doubled the render time)
        w.cycles.sampling_method = "MANUAL"
        w.cycles.sample_map_resolution = 16
    bpy.context.scene.world = w


# ------------------------------------------------------------------ furniture and things
def bookcase(b: Builder, x: float, floor: float, z: float, width: float, height: float, facing: float = 0.0):
    """A bookcase standing on the floor, its front at depth -z, shelves of
    books of varied sizes, some leaning, a box or two among them."""
    depth = 0.3
    rot = (0.0, facing, 0.0)
    books = int(b.rng.integers(10, 21))         # the bookcase must leave most of the budget to the rest
    mat = b.material("bookcase", height)
    for side in (-1, 1):
        b.box("case-side", (x + side * width / 2, floor + height / 2, z - depth / 2), (0.015, height / 2, depth / 2),
              rotation=rot, mat=mat)
    n_shelves = int(b.rng.integers(3, 6))
    gap = height / n_shelves
    for k in range(n_shelves + 1):
        y = floor + min(k * gap, height - 0.015)
        b.box("shelf", (x, y, z - depth / 2), (width / 2, 0.015, depth / 2), rotation=rot, mat=mat)
        if k == n_shelves:
            break
        u = x - width / 2 + 0.03 + b.rng.uniform(0.0, 0.4) * width
        quota = books // (n_shelves - k) if k < n_shelves else 0        # spread over the shelves
        while u < x + width / 2 - 0.05 and quota > 0 and not b.full():
            if b.rng.random() < 0.15:               # a gap or a box among the books
                s = b.rng.uniform(0.04, min(0.12, gap / 2.5))
                b.box("shelf-box", (u + s, y + 0.015 + s, z - depth / 2 + 0.02), (s, s, s * 1.4))
                u += 2 * s + 0.02
                continue
            t = b.rng.uniform(0.015, 0.05)          # a book: thickness, height, depth
            h = b.rng.uniform(0.45, 0.9) * gap
            d = b.rng.uniform(0.15, 0.26)
            lean = b.rng.uniform(-0.25, 0.25) if b.rng.random() < 0.2 else 0.0
            b.box("book", (u + t, y + 0.015 + h / 2, z - depth + d / 2 + 0.02), (t, h / 2, d / 2),
                  rotation=(0.0, 0.0, lean), material_kind=None)
            u += 2 * t + b.rng.uniform(0.0, 0.01)
            books -= 1
            quota -= 1
    b.box("case-back", (x, floor + height / 2, z - depth + 0.005), (width / 2, height / 2, 0.005), mat=mat)


def table(b: Builder, x: float, floor: float, z: float, half_w: float, half_d: float, height: float = 0.75):
    """A table top on four thin legs; returns the top's height (y)."""
    top = floor + height
    if b.full(5):
        return top
    mat = b.material("table", 2 * half_w)
    b.box("table-top", (x, top - 0.02, z), (half_w, 0.02, half_d), mat=mat)
    leg = b.rng.uniform(0.018, 0.035)
    for sx in (-1, 1):
        for sz in (-1, 1):
            b.box("table-leg", (x + sx * (half_w - 0.05), floor + (height - 0.04) / 2, z + sz * (half_d - 0.05)),
                  (leg, (height - 0.04) / 2, leg), mat=mat)
    return top


def chair(b: Builder, x: float, floor: float, z: float, turn: float):
    """Seat, back of bars, four thin legs."""
    if b.full(9):
        return
    mat = b.material("chair", 0.9)
    seat = floor + 0.45
    rot = (0.0, turn, 0.0)
    b.box("chair-seat", (x, seat, z), (0.22, 0.02, 0.22), rotation=rot, mat=mat)
    c, s = math.cos(turn), math.sin(turn)
    for dx, dz in ((-0.19, -0.19), (0.19, -0.19), (-0.19, 0.19), (0.19, 0.19)):
        px, pz = x + c * dx + s * dz, z - s * dx + c * dz
        b.box("chair-leg", (px, floor + 0.22, pz), (0.015, 0.22, 0.015), mat=mat)
    back_x, back_z = x + s * -0.2, z + c * -0.2
    for k in range(int(b.rng.integers(2, 5))):
        off = -0.18 + 0.36 * k / 3
        b.box("chair-bar", (back_x + c * off, seat + 0.22, back_z - s * off), (0.012, 0.22, 0.012), mat=mat)


def things_on(b: Builder, x0: float, x1: float, y: float, z0: float, z1: float, n: int, small: float = 0.12):
    """Small things standing on a surface at height y between x0..x1, z0..z1:
    mugs, bottles, boxes, fruit, books lying flat, a lamp."""
    for i in range(n):
        if b.full():
            return
        x, z = b.rng.uniform(min(x0, x1), max(x0, x1)), b.rng.uniform(min(z0, z1), max(z0, z1))
        s = b.rng.uniform(0.03, small)
        what = b.rng.choice(["mug", "bottle", "box", "fruit", "books", "lamp", "cone"],
                            p=[0.18, 0.14, 0.22, 0.16, 0.14, 0.06, 0.10])
        if what == "mug":
            b.upright("cylinder", "mug", (x, y, z), s * 0.6, s * 1.6)
        elif what == "bottle":
            b.upright("cylinder", "bottle", (x, y, z), s * 0.45, s * 3.0)
            if not b.full():
                b.upright("cylinder", "bottle-neck", (x, y + s * 3.0, z), s * 0.18, s * 1.2)
        elif what == "box":
            h = s * b.rng.uniform(0.5, 2.0)
            b.box("box", (x, y + h, z), (s * b.rng.uniform(0.7, 1.5), h, s), rotation=(0, b.rng.uniform(0, 3.1), 0))
        elif what == "fruit":
            b.add("sphere", "fruit", (x, y + s * 0.6, z), (s * 0.6, s * 0.6, s * 0.6))
        elif what == "books":
            h = y
            for _ in range(int(b.rng.integers(1, 4))):
                if b.full():
                    break
                t = b.rng.uniform(0.01, 0.03)
                b.box("book-flat", (x, h + t, z), (s * 1.3, t, s), rotation=(0, b.rng.uniform(-0.4, 0.4), 0))
                h += 2 * t
        elif what == "lamp":
            b.upright("cylinder", "lamp-pole", (x, y, z), 0.01, s * 5)
            if not b.full():
                b.upright("cone", "lamp-shade", (x, y + s * 5, z), s * 1.2, s * 1.2)
        else:
            b.upright("cone", "cone", (x, y, z), s * 0.6, s * 1.8)


def plant(b: Builder, x: float, floor: float, z: float, height: float):
    """A pot, thin stems and flattened leaves: fine structure against what
    lies behind it."""
    if b.full(3):
        return
    pot = height * 0.25
    b.upright("cylinder", "pot", (x, floor, z), pot * 0.55, pot)
    for i in range(int(b.rng.integers(2, 6))):
        if b.full(2):
            return
        lean_x, lean_z = b.rng.uniform(-0.35, 0.35), b.rng.uniform(-0.35, 0.0)   # leaning away: nothing nearer than the pot
        h = height * b.rng.uniform(0.5, 1.0)
        b.add("cylinder", "stem", (x + lean_x * h / 2, floor + pot + h / 2, z + lean_z * h / 2),
              (0.006, 0.006, h / 2), (math.pi / 2 + lean_z, 0.0, -lean_x))
        leaf = b.rng.uniform(0.04, 0.12) * height
        b.add("sphere", "leaf", (x + lean_x * h, floor + pot + h, z + lean_z * h),
              (leaf, leaf * 0.15, leaf * 0.5), (b.rng.uniform(-1, 1), b.rng.uniform(0, 3.1), b.rng.uniform(-1, 1)))


def poster(b: Builder, x: float, y: float, z: float, w: float, h: float, facing: float = 0.0):
    """A thin board on a wall (a picture, a poster, a notice with text)."""
    b.box("poster", (x, y, z), (w / 2, h / 2, 0.006), rotation=(0.0, facing, 0.0))


# ------------------------------------------------------------------ the recipes
def room(b: Builder) -> None:
    """Indoor: a room 3.4-5 m deep (NYU-like depths), the camera 1.0-1.5 m
    above the floor. A bookcase on the back wall, a table with things on it
    and chairs at 1.5-3.5 m, plants, posters, floor clutter at 2.8-4.5 m,
    and one or two near occluders at 0.75-1.3 m (a pole, a chair back, a
    plant) at the frame's side. Ceiling and window-like area lights. At a
    46 degree vertical field the floor enters the frame beyond ~2.8 m, so
    near things must stand tall."""
    rng = b.rng
    cam_h = rng.uniform(1.0, 1.5)
    floor, ceiling = -cam_h, 2.6 - cam_h
    back = rng.uniform(3.4, 5.0)
    half_w = rng.uniform(1.7, 2.4)
    b.box("floor", (0, floor - 0.01, -back / 2), (half_w, 0.01, back / 2 + 0.5), shell=True)
    b.box("ceiling", (0, ceiling + 0.01, -back / 2), (half_w, 0.01, back / 2 + 0.5), shell=True)
    b.box("back-wall", (0, (floor + ceiling) / 2, -back - 0.01), (half_w, (ceiling - floor) / 2, 0.01), shell=True)
    for side in (-1, 1):
        b.box("side-wall", (side * (half_w + 0.01), (floor + ceiling) / 2, -back / 2),
              (0.01, (ceiling - floor) / 2, back / 2 + 0.5), shell=True)
    # near occluders at the frame's side, tall enough to enter the frame
    for k in range(int(rng.integers(1, 3))):
        near(b, floor, ceiling)
    # the middle: a table with things, chairs
    tz = -rng.uniform(1.4, min(2.8, back - 0.9))
    tx = rng.uniform(-0.5, 0.5)
    hw, hd = rng.uniform(0.4, 0.8), rng.uniform(0.3, 0.5)
    top = table(b, tx, floor, tz, hw, hd, rng.uniform(0.7, 0.8))
    things_on(b, tx - hw + 0.08, tx + hw - 0.08, top, tz - hd + 0.08, tz + hd - 0.08, int(rng.integers(4, 10)))
    # the back wall: a bookcase, posters
    bw = rng.uniform(0.9, 1.8)
    bx = rng.uniform(-half_w + bw / 2, half_w - bw / 2)
    bookcase(b, bx, floor, -back + 0.32, bw, rng.uniform(1.4, 2.2))
    for i in range(int(rng.integers(1, 4))):
        w, h = rng.uniform(0.3, 0.9), rng.uniform(0.3, 0.9)
        poster(b, rng.uniform(-half_w + w, half_w - w), rng.uniform(floor + 1.3, ceiling - h / 2 - 0.1),
               -back + 0.02, w, h)
    for k in range(int(rng.integers(0, 3))):
        chair(b, tx + rng.choice([-1, 1]) * (hw + 0.25), floor, tz + rng.uniform(-0.3, 0.3), rng.uniform(-1.8, 1.8))
    # a cabinet or a sofa-like block at one side, nearer than the table
    if rng.random() < 0.6:
        cw, ch = rng.uniform(0.4, 0.8), rng.uniform(0.45, 1.1)
        b.box("cabinet", (rng.choice([-1, 1]) * rng.uniform(0.7, 1.3), floor + ch / 2, -rng.uniform(1.3, 2.4)),
              (cw / 2, ch / 2, rng.uniform(0.25, 0.45)))
    # plants and floor clutter
    for k in range(int(rng.integers(1, 3))):
        plant(b, rng.uniform(-half_w + 0.3, half_w - 0.3), floor, -rng.uniform(2.0, back - 0.4),
              rng.uniform(0.6, 1.4))
    for k in range(int(rng.integers(2, 6))):
        if b.full():
            break
        s = rng.uniform(0.12, 0.35)
        x, z = rng.uniform(-half_w + s, half_w - s), -rng.uniform(2.8, back - s)
        if rng.random() < 0.6:
            b.box("floor-box", (x, floor + s, z), (s * rng.uniform(0.8, 1.6), s, s), rotation=(0, rng.uniform(0, 3), 0))
        else:
            b.add("sphere", "ball", (x, floor + s, z), (s, s, s))
    # whatever object budget is left: things on a sideboard by a side wall
    if not b.full(6):
        side = rng.choice([-1, 1])
        sz = -rng.uniform(2.0, back - 0.5)
        sx = side * (half_w - 0.3)
        b.box("sideboard", (sx, floor + 0.4, sz), (0.25, 0.4, 0.5))
        things_on(b, sx - 0.2, sx + 0.2, floor + 0.8, sz - 0.45, sz + 0.45, int(rng.integers(3, 8)))
    add_light("AREA", (0, ceiling - 0.05, -back / 2), 60.0 * back, rotation=(0, 0, 0), size=1.5)
    add_light("AREA", (rng.choice([-1, 1]) * (half_w - 0.05), floor + 1.5, -rng.uniform(1.0, back - 1.0)),
              rng.uniform(40.0, 150.0), rotation=(0, rng.choice([-1, 1]) * math.pi / 2, 0), size=1.2)
    world((0.05, 0.05, 0.06), 0.3)


def near(b: Builder, floor: float, top_max: float):
    """A tall, thin thing at 0.75-1.3 m at the frame's side: a pole, a
    shelf's edge, a plant, a chair's back."""
    rng = b.rng
    z = -rng.uniform(0.75, 1.3)
    x = float(rng.choice([-1.0, 1.0])) * rng.uniform(0.25, 0.5) * -z
    what = rng.choice(["pole", "edge", "plant", "chair"])
    # z is the front's depth: every part lies behind it
    if what == "pole":
        r = rng.uniform(0.015, 0.05)
        b.upright("cylinder", "near-pole", (x, floor, z - r), r, rng.uniform(1.5, top_max - floor))
    elif what == "edge":
        s, half_d = rng.uniform(0.02, 0.06), rng.uniform(0.05, 0.2)
        h = rng.uniform(1.4, top_max - floor)
        b.box("near-edge", (x, floor + h / 2, z - half_d), (s, h / 2, half_d))
    elif what == "plant":
        plant(b, x, floor, z, rng.uniform(1.1, 1.6))
    else:
        chair(b, x, floor + 0.5, z - 0.35, rng.uniform(-0.5, 0.5))


def tabletop(b: Builder) -> None:
    """Close-up of a desk: the camera 0.3-0.45 m above a table that runs to
    a wall at 1.7-2.8 m; 15-40 things on it at 0.75-1.7 m (mugs, bottles,
    boxes, fruit, books, a lamp, a plant), a shelf and posters on the wall."""
    rng = b.rng
    y = -rng.uniform(0.3, 0.45)
    wall = rng.uniform(1.7, 2.8)
    b.box("table", (0, y - 0.02, -wall / 2 - 0.2), (1.6, 0.02, wall / 2 + 0.2), shell=True)
    b.box("wall", (0, y + 1.0, -wall - 0.01), (2.5, 1.6, 0.01), shell=True)
    things_on(b, -0.6, 0.6, y, -0.75, -1.1, int(rng.integers(6, 12)), small=0.07)
    things_on(b, -1.0, 1.0, y, -1.1, -1.7, int(rng.integers(8, 16)), small=0.1)
    things_on(b, -1.2, 1.2, y, -1.7, -wall + 0.15, int(rng.integers(4, 10)), small=0.12)
    if not b.full(10):
        plant(b, rng.uniform(-0.6, 0.6), y, -rng.uniform(1.0, wall - 0.2), rng.uniform(0.3, 0.6))
    # a wall shelf with books and posters
    sy = y + rng.uniform(0.4, 0.8)
    shelf_w = rng.uniform(0.6, 1.4)
    sx = rng.uniform(-0.8, 0.8)
    b.box("wall-shelf", (sx, sy, -wall + 0.12), (shelf_w / 2, 0.015, 0.12))
    u = sx - shelf_w / 2 + 0.02
    while u < sx + shelf_w / 2 - 0.04 and not b.full():
        t, h = rng.uniform(0.012, 0.04), rng.uniform(0.15, 0.3)
        b.box("book", (u + t, sy + 0.015 + h / 2, -wall + 0.12), (t, h / 2, rng.uniform(0.07, 0.11)))
        u += 2 * t + rng.uniform(0.0, 0.008)
    for i in range(int(rng.integers(1, 3))):
        if b.full():
            break
        w, h = rng.uniform(0.2, 0.6), rng.uniform(0.2, 0.6)
        poster(b, rng.uniform(-1.2, 1.2), y + rng.uniform(0.3, 1.0), -wall + 0.02, w, h)
    add_light("AREA", (0.3, y + 1.3, -0.8), rng.uniform(20.0, 60.0), rotation=(-1.2, 0, 0), size=1.0)
    add_light("AREA", (rng.choice([-1, 1]) * 1.5, y + 0.8, -wall / 2), rng.uniform(15.0, 60.0),
              rotation=(0, rng.choice([-1, 1]) * math.pi / 2, 0), size=1.0)
    world((0.6, 0.6, 0.65), 0.3)


FACADES = ("bricks", "tiles", "stones")      # structured: plaster and plain noise look flat beyond 10 m
PAVING = ("stones", "tiles", "bricks")


def street(b: Builder) -> None:
    """Outdoor: a street between rows of buildings, the camera off its
    centre (one row of facades from 4-8 m on), a building across its end
    at 25-45 m, pavements, parked cars at 4-18 m, trees, lamp posts,
    signs, bins, benches and bollards at 3-20 m; a cloudy sky at infinity
    shows over the lower roofs."""
    rng = b.rng
    ground = -rng.uniform(1.4, 1.8)
    road = rng.uniform(3.0, 4.5)                       # half width of the road, m
    walk = rng.uniform(1.5, 3.0)                       # pavement width, m
    end = rng.uniform(25.0, 45.0)
    b.box("road", (0, ground - 0.01, -end / 2), (road + walk + 1, 0.01, end / 2 + 1), prefer=PAVING, shell=True)
    for side in (-1.0, 1.0):
        b.box("pavement", (side * (road + walk / 2), ground + 0.07, -end / 2), (walk / 2, 0.08, end / 2),
              prefer=PAVING, shell=True)
        z = -rng.uniform(2.0, 6.0)
        while z > -end and not b.full(2):
            length, h = rng.uniform(5.0, 16.0), rng.uniform(6.0, 22.0)
            depth = rng.uniform(4.0, 10.0)
            front = road + walk + rng.uniform(0.0, 1.2)
            b.box("building", (side * (front + depth), ground + h / 2, z - length / 2), (depth, h / 2, length / 2),
                  prefer=FACADES)
            z -= length + (rng.uniform(1.0, 6.0) if rng.random() < 0.3 else 0.0)
    # tall: sky shows only above low buildings (a strip of soft sky at the end put a fifth of the crops
    # above 40 dB and lowered the fine-texture share from 8.4 to 6.8 %)
    across = rng.uniform(24.0, 36.0)
    b.box("building-across", (0, ground + across / 2, -end - 5), (road + walk + 20, across / 2, 5), prefer=FACADES,
          shell=True)
    for i in range(int(rng.integers(3, 7))):
        car(b, rng.choice([-1.0, 1.0]) * (road - rng.uniform(0.9, 1.3)), ground, -rng.uniform(4.0, 18.0))
    for i in range(int(rng.integers(2, 6))):
        if b.full(5):
            break
        z, x = -rng.uniform(4.0, 25.0), rng.choice([-1.0, 1.0]) * (road + rng.uniform(0.5, walk - 0.3))
        b.upright("cylinder", "trunk", (x, ground, z), rng.uniform(0.1, 0.25), rng.uniform(1.5, 3.0))
        for k in range(int(rng.integers(2, 5))):
            r = rng.uniform(0.6, 1.5)
            b.add("sphere", "crown", (x + rng.uniform(-0.8, 0.8), ground + rng.uniform(2.5, 4.0), z + rng.uniform(-0.8, 0.8)),
                  (r, r * rng.uniform(0.7, 1.1), r))
    for i in range(int(rng.integers(10, 24))):
        if b.full(2):
            break
        z, x = -rng.uniform(3.0, 20.0), rng.choice([-1.0, 1.0]) * (road + rng.uniform(0.3, walk - 0.2))
        what = rng.choice(["lamp", "sign", "bin", "bollard", "bench"])
        if what == "lamp":
            b.upright("cylinder", "lamp-post", (x, ground, z), 0.06, rng.uniform(3.5, 6.0))
        elif what == "sign":
            h = rng.uniform(1.8, 2.6)
            b.upright("cylinder", "sign-post", (x, ground, z), 0.03, h)
            b.box("sign", (x, ground + h + 0.25, z), (rng.uniform(0.2, 0.45), 0.25, 0.01), material_kind="text")
        elif what == "bin":
            b.upright("cylinder", "bin", (x, ground, z), 0.3, 0.9)
        elif what == "bench":
            b.box("bench", (x, ground + 0.45, z), (0.25, 0.04, 0.9))
            b.box("bench-back", (x + 0.2 * np.sign(x), ground + 0.7, z), (0.03, 0.25, 0.9))
        else:
            b.upright("cylinder", "bollard", (x, ground, z), 0.08, 0.9)
    # the camera stands off the street's centre: one row of facades comes near
    shift = rng.choice([-1.0, 1.0]) * rng.uniform(1.0, road + walk * 0.5)
    for obj in _bpy().context.scene.objects:
        obj.location.x += shift
    add_light("SUN", (0, 10, 0), rng.uniform(2.0, 4.0), rotation=(rng.uniform(0.6, 1.1), 0.1, rng.uniform(-0.6, 0.6)))
    world((0.45, 0.6, 0.9), 1.0, clouds_rng=rng)


def car(b: Builder, x: float, ground: float, z: float):
    """A parked car: body, cabin, four wheels."""
    if b.full(6):
        return
    rng = b.rng
    length, width = rng.uniform(1.9, 2.3), rng.uniform(0.8, 0.95)
    body = b.material("car", 2 * length)
    b.box("car-body", (x, ground + 0.55, z), (width, 0.3, length), mat=body)
    b.box("car-cabin", (x, ground + 1.1, z + rng.uniform(-0.3, 0.3)), (width * 0.92, 0.27, length * 0.55))
    tyre = b.material("tyre", 0.6)
    for sx in (-1, 1):
        for sz in (-1, 1):
            b.add("cylinder", "wheel", (x + sx * width, ground + 0.32, z + sz * length * 0.65), (0.32, 0.32, 0.1),
                  (0.0, math.pi / 2, 0.0), mat=tyre)


def plane_at(b: Builder, distance_m: float = 2.5) -> None:
    """A fronto-parallel textured plane at ``distance_m`` (for checks)."""
    b.add("plane", "plane", (0, 0, -distance_m), (50, 50, 1), material_kind=None, shell=True)
    add_light("SUN", (0, 0, 5), 2.0)
    world((0.0, 0.0, 0.0), 0.0)


@dataclass(frozen=True)
class Recipe:
    """A scene recipe: ``build`` fills the bpy scene (None: drawn in numpy,
    not by Blender); ``indoor`` recipes aim at >= 60 % of the pixels at
    1-5 m, like indoor RGB-D data (NYU Depth v2)."""
    name: str
    build: Callable | None
    indoor: bool
    summary: str


RECIPES = {r.name: r for r in (
    Recipe("room", room, True, "a furnished room 3.4-5 m deep, 20-60 objects at 0.75-5 m"),
    Recipe("tabletop", tabletop, True, "a desk's clutter at 0.75-1.7 m before a wall at 1.7-2.8 m"),
    Recipe("street", street, False, "facades, parked cars, trees, posts at 3-45 m, sky over low roofs"),
    Recipe("leaves", None, False, "dead leaves in numpy: textured shapes at log-uniform 0.7-10 m"),
    Recipe("plane", plane_at, False, "a fronto-parallel plane at 2.5 m (for checks)"),
)}


def build(recipe: str, rng, textures=None) -> Builder:
    """Fill the (empty) bpy scene with ``recipe``; returns its Builder
    (material records, object count)."""
    r = RECIPES[recipe]
    if r.build is None:
        raise ValueError(f"recipe {recipe!r} is not a Blender scene")
    _BASE_MESHES.clear()
    b = Builder(rng=rng, textures=textures)
    r.build(b)
    return b

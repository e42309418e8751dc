"""Procedural surface materials with detail at every scale, and image textures.

``surface_material(name, rng, kind=..., textures=..., size_m=...)`` builds one
Blender material from shader nodes only (nothing downloaded), every value
drawn from the numpy Generator ``rng`` in a fixed order, so the same
generator state gives the same node values. Kinds (``KINDS``): multi-octave
noise, bricks, tiles, wood, stones (Voronoi cells), fabric (a weave of two
perpendicular thread bands under a plaid), printed text (lines of glyph-like
marks on labels), plaster (paint with a fine grain); or, given a
``TextureLibrary``, a user's image set (kind ``"image"``).

Every kind has several colours (a palette of 4-6 related colours, not a
two-colour ramp), a bump driven by its pattern and a varying roughness.
Detail spans pixel to object: patches of colour from the object's size
(``size_m``) over three octaves, the kind's own structure (bricks, boards,
cells, stripes, lines of text: cm to dm), and a fine layer of noise octaves
from a few cm down to ``FINEST_M`` (2 mm) with nearly equal amplitude per
octave, which mottles the colour and, thresholded, makes sharp flecks and
pores. The factory's lenses see 1.4-1.8 mm per pixel at 1 m (35 um pixels,
20-25 mm focal length at 480 x 640), so the texture reaches the pixel at the
nearest depths. No displacement, no volumes; camera rays alone see the
pattern, other rays a plain BSDF of the palette's mean colour (see
``_camera_only``), which keeps the cost to a few texture evaluations per
pixel sample.

Printed text is a shader imitation (lines of glyph-like dot patterns on
label panels), not FONT objects: it works on any face of any object the
recipes make, needs no placement or extra geometry from them, and cannot
z-fight with the face it is printed on; what it gives up is real letter
shapes, which the frame statistics do not need.

Textures are placed in world coordinates in metres (the primitives are
scaled, so UVs and object coordinates are not metric), through a planar
projection along the face's dominant axis, chosen so that the second
coordinate is the height (y) on every vertical face (brick rows and text
lines run horizontally) and the depth (z) on floors and ceilings. Images use
the same projection instead of the image node's BOX mode, whose blend uses
the object-space normal and so projects along the wrong axis on a rotated
plane; their normal maps are turned into world space through the same frame.
"""
from __future__ import annotations

import colorsys
import math
from pathlib import Path

import numpy as np

KINDS = ("noise", "bricks", "tiles", "wood", "stones", "fabric", "text", "plaster")
FINEST_M = 0.002            # finest grain feature, m (about one pixel at 1 m)
MAX_OCTAVES = 15.0          # Blender's limit of a Noise texture's Detail
FINE_TOP_M = 0.05           # the colour patches stop here, m: the fine layers take over
PATCH_OCTAVES = 3.0         # the patches' octaves at most (render cost)
LABEL_MAX_M = 1.5           # labels and posters scale with the object up to this size, m
WAVE_PERIOD = 2 * math.pi / 20     # a Wave texture's period at Scale 1 (its phase is 20 x the coordinate)


def _bpy():
    import bpy
    return bpy


# ------------------------------------------------------------------ node building
class _Graph:
    """A material's node tree with short helpers; sockets in, sockets out."""

    def __init__(self, mat):
        self.tree = mat.node_tree
        self.bsdf = next(n for n in self.tree.nodes if n.bl_idname == "ShaderNodeBsdfPrincipled")
        self.colours: list[np.ndarray] = []         # every palette drawn: their mean is the indirect colour

    def palette(self, rng, kind: str, n: int) -> list[np.ndarray]:
        cols = palette(rng, kind, n)
        self.colours += cols
        return cols

    def node(self, kind: str, inputs: dict | None = None, **props):
        n = self.tree.nodes.new(kind)
        for k, v in props.items():
            setattr(n, k, v)
        for k, v in (inputs or {}).items():
            self.set(n.inputs[k], v)
        return n

    def set(self, socket, value) -> None:
        if hasattr(value, "is_output"):
            self.tree.links.new(value, socket)
        elif isinstance(value, (tuple, list, np.ndarray)):
            v = [float(x) for x in value]
            socket.default_value = v + [1.0] if socket.type == "RGBA" and len(v) == 3 else v
        else:
            socket.default_value = float(value)

    def math(self, op: str, a, b=0.0, clamp: bool = False):
        n = self.node("ShaderNodeMath", operation=op, use_clamp=clamp)
        self.set(n.inputs[0], a)
        self.set(n.inputs[1], b)
        return n.outputs[0]

    def vmath(self, op: str, a, b=None, scale=None):
        n = self.node("ShaderNodeVectorMath", operation=op)
        self.set(n.inputs[0], a)
        if b is not None:
            self.set(n.inputs[1], b)
        if scale is not None:
            self.set(n.inputs["Scale"], scale)
        return n.outputs[0] if op not in ("DOT_PRODUCT", "LENGTH", "DISTANCE") else n.outputs["Value"]

    def mix(self, factor, a, b, blend: str = "MIX"):
        """Colour mix (ShaderNodeMix, RGBA: inputs 6, 7 are A, B)."""
        n = self.node("ShaderNodeMix", data_type="RGBA", blend_type=blend, clamp_result=True)
        self.set(n.inputs[0], factor)
        self.set(n.inputs[6], a)
        self.set(n.inputs[7], b)
        return n.outputs[2]

    def ramp(self, factor, stops, interpolation: str = "LINEAR"):
        """A colour ramp through ``stops`` [(position 0-1, linear RGB)]."""
        n = self.node("ShaderNodeValToRGB")
        cr = n.color_ramp
        cr.interpolation = interpolation
        while len(cr.elements) < len(stops):
            cr.elements.new(0.5)
        for e, (pos, rgb) in zip(cr.elements, sorted(stops, key=lambda s: s[0])):
            e.position = float(pos)
            e.color = (*(float(c) for c in rgb), 1.0)
        self.set(n.inputs["Factor"], factor)
        return n.outputs["Color"]

    def remap(self, value, lo, hi, to_lo=0.0, to_hi=1.0, clamp: bool = True):
        return self.node("ShaderNodeMapRange", {"Value": value, "From Min": lo, "From Max": hi,
                                                "To Min": to_lo, "To Max": to_hi}, clamp=clamp).outputs["Result"]

    def xyz(self, x=0.0, y=0.0, z=0.0):
        return self.node("ShaderNodeCombineXYZ", {"X": x, "Y": y, "Z": z}).outputs[0]


class _Frame:
    """World position (m) and, built on first use, the planar frame of the
    face's dominant axis: ``uvw`` = (u, v, 0) metres across the face (v the
    height on vertical faces), ``tangent`` and ``bitangent`` their world
    directions; ``normal`` the geometric normal. Kept to a few nodes: every
    node costs render time, thrice over inside a bump's height."""

    def __init__(self, g: _Graph, offset):
        self.g = g
        geo = g.node("ShaderNodeNewGeometry")
        self.position = g.vmath("ADD", geo.outputs["Position"], tuple(offset))
        self.normal = geo.outputs["True Normal"]
        self._uvw = self._axes = None

    def _dominant(self):
        """(is_x, is_y): 1 where the normal's x (or y) component dominates."""
        if self._axes is None:
            g = self.g
            a = g.node("ShaderNodeSeparateXYZ", {"Vector": g.vmath("ABSOLUTE", self.normal)}).outputs
            self._axes = (g.math("GREATER_THAN", a[0], g.math("MAXIMUM", a[1], a[2])),
                          g.math("GREATER_THAN", a[1], g.math("MAXIMUM", a[0], a[2])))
        return self._axes

    @property
    def uvw(self):
        if self._uvw is None:
            g = self.g
            is_x, is_y = self._dominant()
            p = g.node("ShaderNodeSeparateXYZ", {"Vector": self.position}).outputs
            # x-dominant faces: (z, y); y-dominant: (x, z); otherwise (x, y)
            u = g.node("ShaderNodeMath", operation="MULTIPLY_ADD")
            g.set(u.inputs[0], is_x), g.set(u.inputs[1], g.math("SUBTRACT", p[2], p[0])), g.set(u.inputs[2], p[0])
            v = g.node("ShaderNodeMath", operation="MULTIPLY_ADD")
            g.set(v.inputs[0], is_y), g.set(v.inputs[1], g.math("SUBTRACT", p[2], p[1])), g.set(v.inputs[2], p[1])
            self._uvw = g.xyz(u.outputs[0], v.outputs[0], 0.0)
        return self._uvw

    @property
    def tangent(self):
        is_x, _ = self._dominant()
        return self.g.xyz(self.g.math("SUBTRACT", 1.0, is_x), 0.0, is_x)

    @property
    def bitangent(self):
        _, is_y = self._dominant()
        return self.g.xyz(0.0, self.g.math("SUBTRACT", 1.0, is_y), is_y)


# ------------------------------------------------------------------ colours and shared layers
def _linear(rgb_srgb) -> np.ndarray:
    c = np.clip(np.asarray(rgb_srgb, np.float64), 0.0, 1.0)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


# per kind: (hue range, saturation range, value range), HSV of sRGB; hue None = any
_PALETTES = {
    "noise": (None, (0.05, 0.6), (0.25, 0.85)),
    "bricks": ((0.0, 0.08), (0.35, 0.7), (0.3, 0.7)),
    "tiles": (None, (0.0, 0.5), (0.35, 0.92)),
    "wood": ((0.05, 0.11), (0.4, 0.75), (0.25, 0.75)),
    "stones": ((0.05, 0.15), (0.03, 0.3), (0.25, 0.8)),
    "fabric": (None, (0.2, 0.8), (0.2, 0.85)),
    "text": ((0.08, 0.14), (0.05, 0.35), (0.7, 0.92)),
    "plaster": (None, (0.02, 0.2), (0.7, 0.92)),
}


def palette(rng, kind: str, n: int) -> list[np.ndarray]:
    """``n`` related colours (linear RGB, each channel 0-0.83): one hue
    from the kind's range, each colour's hue, saturation and value jittered."""
    hues, sats, vals = _PALETTES[kind]
    h0 = rng.uniform(*hues) if hues else rng.uniform(0.0, 1.0)
    s0, v0 = rng.uniform(*sats), rng.uniform(*vals)
    out = []
    for _ in range(n):
        h = (h0 + rng.normal(0.0, 0.025)) % 1.0
        s = float(np.clip(s0 + rng.normal(0.0, 0.12), 0.0, 1.0))
        v = float(np.clip(v0 * rng.uniform(0.6, 1.25), 0.08, 0.92))
        out.append(_linear(colorsys.hsv_to_rgb(h, s, v)))
    return out


def _stops(rng, colours) -> list[tuple[float, np.ndarray]]:
    """Ramp stops: the colours at sorted random positions spanning 0-1."""
    pos = np.sort(rng.uniform(0.0, 1.0, len(colours)))
    pos = (pos - pos[0]) / max(pos[-1] - pos[0], 1e-6)
    return list(zip(pos, colours))


def octaves(size_m: float, finest_m: float = FINEST_M) -> float:
    """Noise octaves (Detail) from features of ``size_m`` down to ``finest_m``."""
    return float(np.clip(math.log2(max(size_m, finest_m) / finest_m), 0.0, MAX_OCTAVES))


def _noise(g: _Graph, vector, feature_m: float, detail: float, roughness: float):
    """2-D fBm Noise texture on the face's plane (half a 3-D noise's cost):
    Factor about 0.5 +- 0.15, features from ``feature_m`` metres over
    ``detail`` octaves (each half the last)."""
    return g.node("ShaderNodeTexNoise", {"Vector": vector, "Scale": 1.0 / feature_m, "Detail": detail,
                                         "Roughness": roughness, "Lacunarity": 2.0, "Distortion": 0.0},
                  noise_dimensions="2D", normalize=True).outputs["Factor"]


def _stretch(g: _Graph, fac, contrast: float):
    """A Noise Factor (about 0.5 +- 0.15) stretched to 0-1: +-0.25 / contrast -> 0-1."""
    half = 0.25 / contrast
    return g.remap(fac, 0.5 - half, 0.5 + half)


def _patches(g: _Graph, f: _Frame, rng, size_m: float, contrast: float):
    """Large-scale variation, 0-1: fBm from the object's size down to
    FINE_TOP_M, at most PATCH_OCTAVES octaves (cost)."""
    fac = _noise(g, f.uvw, size_m, min(octaves(size_m, FINE_TOP_M), PATCH_OCTAVES), rng.uniform(0.6, 0.75))
    return _stretch(g, fac, contrast)


def _fine(g: _Graph, vector, rng, top_m: float = 0.0, contrast: float = 1.5):
    """The detail every kind overlays: fBm from ``top_m`` metres (default a
    seeded 2.5-5 cm) down to FINEST_M with nearly equal amplitude per
    octave (as in photographs), 0-1."""
    top_m = top_m or rng.uniform(0.025, 0.05)
    return _stretch(g, _noise(g, vector, top_m, octaves(top_m), rng.uniform(0.9, 1.0)), contrast)


def _relief(g: _Graph, f: _Frame, rng):
    """A bump height of its own for grain-only surfaces: one octave of 3-D
    noise of a seeded 4-10 mm on the position. The bump evaluates its
    height thrice, so it takes neither the colour's grain nor the planar
    frame's dozen nodes."""
    return g.node("ShaderNodeTexNoise", {"Vector": f.position, "Scale": 1.0 / rng.uniform(0.004, 0.01),
                                         "Detail": 0.0, "Roughness": 0.5, "Lacunarity": 2.0, "Distortion": 0.0},
                  noise_dimensions="3D", normalize=True).outputs["Factor"]


def _finish(g: _Graph, colour, roughness, height, bump_m: float, bump_strength: float = 1.0,
            invert: bool = False) -> None:
    """Colour, roughness and a bump of ``height`` (0-1, times ``bump_m``
    metres; ``invert``: 1 is low). Heights come from the pattern's cheapest
    nodes: Cycles evaluates a bump's height three times. Only camera rays
    see the pattern (see _camera_only)."""
    g.set(g.bsdf.inputs["Base Color"], colour)
    g.set(g.bsdf.inputs["Roughness"], roughness)
    bump = g.node("ShaderNodeBump", {"Height": height, "Distance": bump_m, "Strength": bump_strength},
                  invert=invert)
    g.set(g.bsdf.inputs["Normal"], bump.outputs["Normal"])
    _camera_only(g)


def _camera_only(g: _Graph) -> None:
    """Camera rays get the patterned BSDF, every other ray (diffuse and
    glossy bounces) a plain one of the palette's mean colour. Cycles skips
    the unused side of a Mix Shader whose factor is 0 or 1, so the texture
    nodes run once per pixel sample instead of at every bounce (measured
    with blender_addon.tools.material_texture, kinds drawn: 9.6 -> 8.8 CPU
    s per 480 x 640 frame); bounce light averages many surface points,
    which the mean colour stands for. Glossy reflections of a patterned
    surface show its mean colour."""
    out = next(n for n in g.tree.nodes if n.bl_idname == "ShaderNodeOutputMaterial")
    flat = g.node("ShaderNodeBsdfPrincipled", {"Base Color": np.mean(g.colours, axis=0), "Roughness": 0.7})
    mix = g.node("ShaderNodeMixShader", {"Factor": g.node("ShaderNodeLightPath").outputs["Is Camera Ray"]})
    g.tree.links.new(flat.outputs[0], mix.inputs[1])
    g.tree.links.new(g.bsdf.outputs[0], mix.inputs[2])
    g.tree.links.new(mix.outputs[0], out.inputs["Surface"])


def _mottle(g: _Graph, colour, grain, amount: float):
    """Colour darkened and lightened by a 0-1 grain: an overlay, for the
    colours below 0.5 the colour times 1 +- ``amount`` (one node)."""
    return g.mix(amount, colour, grain, "OVERLAY")


def _specks(g: _Graph, colour, grain, threshold: float, speck_colour):
    """``speck_colour`` where the 0-1 grain exceeds ``threshold`` (sharp-edged
    flecks of every size the grain holds, as in granite or terrazzo)."""
    return g.mix(g.remap(grain, threshold, threshold + 0.03), colour, tuple(speck_colour))


# ------------------------------------------------------------------ the kinds
def _kind_noise(g, f, rng, size_m):
    cols = g.palette(rng, "noise", int(rng.integers(4, 7)))
    patches = _patches(g, f, rng, size_m, rng.uniform(0.4, 0.8))
    colour = g.ramp(patches, _stops(rng, cols))
    fine = _fine(g, f.uvw, rng, rng.uniform(0.02, 0.05), 2.2)
    colour = _mottle(g, colour, fine, rng.uniform(0.6, 0.75))
    colour = _specks(g, colour, fine, rng.uniform(0.72, 0.84), cols[0] * rng.choice([0.25, 1.6]))
    rough = g.remap(g.math("ADD", patches, fine), 0.0, 2.0, *sorted(rng.uniform(0.3, 0.95, 2)))
    _finish(g, colour, rough, _relief(g, f, rng), rng.uniform(0.0005, 0.0015))


def _bricks(g, f, rng, size_m, *, width_m, height_m, mortar_m, offset, kind):
    """(colour, mortar mask (1 in the mortar), fine detail) of bricks or tiles:
    each brick's colour mixed from the mottled palette and a second colour by
    the brick's random tint. The Brick node takes constant colours only, so
    the bump's extra evaluations of the mortar mask stay cheap."""
    cols = g.palette(rng, kind, 5)
    mortar = _linear(np.full(3, rng.uniform(0.35, 0.8))) * rng.uniform(0.8, 1.0, 3)
    brick = g.node("ShaderNodeTexBrick", {"Vector": f.uvw, "Color1": (1, 1, 1), "Color2": (0, 0, 0),
                                          "Mortar": (0, 0, 0), "Scale": 1.0, "Mortar Size": mortar_m,
                                          "Mortar Smooth": rng.uniform(0.05, 0.3), "Bias": rng.uniform(-0.4, 0.4),
                                          "Brick Width": width_m, "Row Height": height_m},
                   offset=offset, offset_frequency=2, squash=1.0, squash_frequency=2)
    tint = g.node("ShaderNodeSeparateColor", {"Color": brick.outputs["Color"]}).outputs["Red"]
    body = g.ramp(_patches(g, f, rng, size_m, rng.uniform(0.8, 1.2)), _stops(rng, cols[:3]))
    mask = brick.outputs["Factor"]
    colour = g.mix(mask, g.mix(tint, tuple(cols[3]), body), tuple(mortar))
    return colour, mask, _fine(g, f.uvw, rng)


def _kind_bricks(g, f, rng, size_m):
    colour, mask, fine = _bricks(g, f, rng, size_m, width_m=rng.uniform(0.19, 0.3),
                                 height_m=rng.uniform(0.055, 0.09), mortar_m=rng.uniform(0.006, 0.014),
                                 offset=rng.uniform(0.4, 0.6), kind="bricks")
    colour = _mottle(g, colour, fine, rng.uniform(0.25, 0.4))
    _finish(g, colour, g.remap(fine, 0.2, 0.8, rng.uniform(0.7, 0.85), 0.98), mask, rng.uniform(0.003, 0.006),
            invert=True)


def _kind_tiles(g, f, rng, size_m):
    side = rng.uniform(0.05, 0.2)
    colour, grout, fine = _bricks(g, f, rng, size_m, width_m=side, height_m=side * rng.choice([1.0, 0.5]),
                                  mortar_m=rng.uniform(0.003, 0.008), offset=0.0, kind="tiles")
    # glazed stoneware: a speckled body (fine mottle) under the glaze
    colour = _mottle(g, colour, fine, rng.uniform(0.35, 0.5))
    gloss = rng.uniform(0.05, 0.35)
    rough = g.math("ADD", g.remap(fine, 0.0, 1.0, gloss, gloss + 0.2), g.math("MULTIPLY", grout, 0.6), clamp=True)
    _finish(g, colour, rough, grout, rng.uniform(0.002, 0.004), invert=True)


def _kind_wood(g, f, rng, size_m):
    cols = g.palette(rng, "wood", 5)
    # the grain runs along u: the rings' distortion and the fibres are stretched along u
    along = g.node("ShaderNodeMapping", {"Vector": f.uvw, "Scale": (rng.uniform(0.03, 0.08), 1.0, 1.0)}).outputs[0]
    rings = g.node("ShaderNodeTexWave", {"Vector": along, "Scale": WAVE_PERIOD / rng.uniform(0.006, 0.02),
                                         "Distortion": rng.uniform(2.0, 6.0), "Detail": 3.0,
                                         "Detail Scale": rng.uniform(0.5, 2.0), "Detail Roughness": 0.6,
                                         "Phase Offset": rng.uniform(0, 2 * math.pi)},
                   wave_type="RINGS", rings_direction="X", wave_profile="SAW").outputs["Factor"]
    streaks = g.node("ShaderNodeMapping", {"Vector": f.uvw, "Scale": (0.05, 1.0, 1.0)}).outputs[0]
    fibre = _fine(g, streaks, rng, 0.03, 1.6)
    mixed = g.math("ADD", g.math("MULTIPLY", rings, 0.5), g.math("MULTIPLY", fibre, 0.5))
    colour = _mottle(g, g.ramp(mixed, _stops(rng, cols)), fibre, rng.uniform(0.3, 0.45))
    colour = _specks(g, colour, fibre, rng.uniform(0.74, 0.84), cols[0] * 0.3)        # pores
    colour = _mottle(g, colour, _patches(g, f, rng, size_m, 1.0), rng.uniform(0.1, 0.2))
    planks = g.node("ShaderNodeTexBrick", {"Vector": f.uvw, "Color1": (1, 1, 1), "Color2": (1, 1, 1),
                                           "Mortar": (0, 0, 0), "Scale": 1.0, "Mortar Size": 0.002,
                                           "Mortar Smooth": 0.2, "Brick Width": rng.uniform(0.8, 2.0),
                                           "Row Height": rng.uniform(0.09, 0.2), "Bias": 0.0},
                    offset=rng.uniform(0.3, 0.7), offset_frequency=1).outputs["Factor"]
    colour = g.mix(g.math("MULTIPLY", planks, 0.6), colour, tuple(cols[0] * 0.25))
    gloss = rng.uniform(0.25, 0.6)
    rough = g.remap(fibre, 0.0, 1.0, gloss, gloss + 0.25)
    _finish(g, colour, rough, planks, rng.uniform(0.001, 0.003), invert=True)


def _kind_stones(g, f, rng, size_m):
    """Pebbles in mortar: 2-D Voronoi cells on the face's plane (a third of a
    3-D Voronoi's cost), a stone where the distance to the cell's centre is
    below a seeded radius, each stone its own palette colour."""
    cols = g.palette(rng, "stones", 6)
    cell_m = rng.uniform(0.02, 0.12)
    cells = g.node("ShaderNodeTexVoronoi", {"Vector": f.uvw, "Scale": 1.0 / cell_m,
                                            "Randomness": rng.uniform(0.7, 1.0)},
                   voronoi_dimensions="2D", feature="F1", distance="EUCLIDEAN")
    which = g.node("ShaderNodeSeparateColor", {"Color": cells.outputs["Color"]}).outputs["Red"]
    stone = g.ramp(which, _stops(rng, cols[:5]))
    radius = rng.uniform(0.45, 0.65)
    inside = g.remap(cells.outputs["Distance"], radius, radius - 0.12)    # 1 inside a stone, 0 in the mortar
    fine = _fine(g, f.uvw, rng, min(cell_m / 2.0, 0.05))
    colour = _mottle(g, g.mix(inside, tuple(cols[5] * 0.3), stone), fine, rng.uniform(0.2, 0.35))
    colour = _mottle(g, colour, _patches(g, f, rng, size_m, 1.0), 0.15)
    rough = g.remap(fine, 0.2, 0.8, rng.uniform(0.5, 0.75), 0.95)
    _finish(g, colour, rough, inside, cell_m * rng.uniform(0.05, 0.1))


def _kind_fabric(g, f, rng, size_m):
    cols = g.palette(rng, "fabric", 5)
    sep = g.node("ShaderNodeSeparateXYZ", {"Vector": f.uvw}).outputs
    thread_m = rng.uniform(0.002, 0.005)

    def bands(coord, period_m):
        wave = g.node("ShaderNodeTexWave", {"Vector": g.xyz(coord, 0.0, 0.0), "Scale": WAVE_PERIOD / period_m,
                                            "Distortion": 0.0, "Detail": 0.0},
                      wave_type="BANDS", bands_direction="X", wave_profile="SIN")
        return wave.outputs["Factor"]

    warp, weft = bands(sep[0], thread_m), bands(sep[1], thread_m)
    # plaid: stripes of the palette's colours at cm periods in each direction
    stripe_u = g.ramp(bands(sep[0], rng.uniform(0.02, 0.12)), _stops(rng, cols[:3]), "CONSTANT")
    stripe_v = g.ramp(bands(sep[1], rng.uniform(0.02, 0.12)), _stops(rng, cols[2:]), "CONSTANT")
    cloth = g.mix(rng.uniform(0.3, 0.7), stripe_u, stripe_v)
    weave = g.math("MAXIMUM", warp, weft)
    fuzz = _fine(g, f.uvw, rng, 0.02, 2.0)
    colour = _mottle(g, _mottle(g, cloth, weave, rng.uniform(0.25, 0.4)), fuzz, 0.3)
    colour = _mottle(g, colour, _patches(g, f, rng, size_m, 1.0), 0.1)
    _finish(g, colour, g.remap(fuzz, 0.0, 1.0, 0.75, 1.0), weave, thread_m * 0.5)


def _glyphs(g: _Graph, f: _Frame, rng, size_m: float):
    """(ink mask 0/1, which of two inks 0/1) of lines of glyph-like marks:
    each glyph cell (a seeded 6-25 mm line height) a random 3 x 5 pattern
    of dots, words split by random spaces, text blocks a third to two
    thirds of the object wide, each line of a random length."""
    line_m = rng.uniform(0.006, 0.025)
    glyph_m = line_m * rng.uniform(0.5, 0.7)
    sep = g.node("ShaderNodeSeparateXYZ", {"Vector": f.uvw}).outputs
    u, v = g.math("DIVIDE", sep[0], glyph_m), g.math("DIVIDE", sep[1], line_m)
    col, row = g.math("FLOOR", u), g.math("FLOOR", v)
    fu, fv = g.math("FRACT", u), g.math("FRACT", v)
    dot_u = g.math("FLOOR", g.math("MULTIPLY", g.remap(fu, 0.1, 0.9), 2.999))
    dot_v = g.math("FLOOR", g.math("MULTIPLY", g.remap(fv, 0.2, 0.8), 4.999))
    inside = g.math("MULTIPLY", g.math("MULTIPLY", g.math("GREATER_THAN", fu, 0.1), g.math("LESS_THAN", fu, 0.9)),
                    g.math("MULTIPLY", g.math("GREATER_THAN", fv, 0.2), g.math("LESS_THAN", fv, 0.8)))
    seed = rng.uniform(0, 1000)

    def white(x, y, w):
        return g.node("ShaderNodeTexWhiteNoise", {"Vector": g.xyz(x, y, seed), "W": w},
                      noise_dimensions="4D").outputs["Value"]

    dot = g.math("GREATER_THAN", white(g.math("ADD", g.math("MULTIPLY", col, 3.0), dot_u),
                                       g.math("ADD", g.math("MULTIPLY", row, 5.0), dot_v), 0.0), 0.4)
    letter = g.math("GREATER_THAN", white(col, row, 1.0), rng.uniform(0.12, 0.22))       # else a space
    block = max(8.0, round(size_m * rng.uniform(0.3, 0.7) / glyph_m))
    block_no = g.math("FLOOR", g.math("DIVIDE", col, block))
    line_len = g.math("MULTIPLY", white(block_no, row, 2.0), block)
    line_on = g.math("MULTIPLY", g.math("GREATER_THAN", white(block_no, row, 3.0), 0.15),
                     g.math("LESS_THAN", g.math("FLOORED_MODULO", col, block), line_len))
    mark = g.math("MULTIPLY", g.math("MULTIPLY", dot, letter), g.math("MULTIPLY", inside, line_on))
    return mark, g.math("GREATER_THAN", white(0.0, row, 4.0), 0.7)


def _kind_text(g, f, rng, size_m):
    """Printed labels: paper panels (bricks with wide margins, a third to
    two thirds of the object or of LABEL_MAX_M) carrying lines of
    glyph-like marks (_glyphs) in one or two inks."""
    paper = g.palette(rng, "text", 4)
    ink = [_linear(colorsys.hsv_to_rgb(rng.uniform(0, 1), rng.uniform(0.0, 0.8), rng.uniform(0.05, 0.35)))
           for _ in range(2)]
    label_m = min(size_m, LABEL_MAX_M)
    mark, second_ink = _glyphs(g, f, rng, label_m)
    panels = g.node("ShaderNodeTexBrick", {"Vector": f.uvw, "Color1": tuple(paper[0]), "Color2": tuple(paper[1]),
                                           "Mortar": tuple(paper[2] * rng.uniform(0.3, 0.7)), "Scale": 1.0,
                                           "Mortar Size": rng.uniform(0.01, 0.03), "Mortar Smooth": 0.0,
                                           "Bias": 0.0, "Brick Width": label_m * rng.uniform(0.3, 0.7),
                                           "Row Height": label_m * rng.uniform(0.15, 0.4)},
                    offset=rng.uniform(0.0, 0.5))
    mark = g.math("MULTIPLY", mark, g.math("SUBTRACT", 1.0, panels.outputs["Factor"]))   # no ink in the margins
    ink_colour = g.mix(second_ink, tuple(ink[0]), tuple(ink[1]))
    fine = _fine(g, f.uvw, rng, 0.02)
    colour = _mottle(g, g.mix(mark, panels.outputs["Color"], ink_colour), fine, rng.uniform(0.15, 0.3))
    gloss = rng.uniform(0.3, 0.7)
    rough = g.math("ADD", g.remap(fine, 0.0, 1.0, gloss, gloss + 0.2), g.math("MULTIPLY", mark, -0.15))
    _finish(g, colour, rough, panels.outputs["Factor"], rng.uniform(0.0005, 0.0015), invert=True)


def _kind_plaster(g, f, rng, size_m):
    cols = g.palette(rng, "plaster", 4)
    tone = g.ramp(_patches(g, f, rng, size_m, rng.uniform(0.25, 0.5)), _stops(rng, cols))    # stains, patches
    # paint over sand-finished plaster: grain of mm to cm, sparse darker grit
    fine = _fine(g, f.uvw, rng, rng.uniform(0.015, 0.035), 2.2)
    colour = _mottle(g, tone, fine, rng.uniform(0.5, 0.65))
    colour = _specks(g, colour, fine, rng.uniform(0.78, 0.86), cols[0] * rng.uniform(0.35, 0.6))   # grit
    rough = g.remap(fine, 0.0, 1.0, rng.uniform(0.55, 0.75), 0.95)
    _finish(g, colour, rough, _relief(g, f, rng), rng.uniform(0.004, 0.008), rng.uniform(0.6, 1.0))     # stucco


_BUILDERS = {"noise": _kind_noise, "bricks": _kind_bricks, "tiles": _kind_tiles, "wood": _kind_wood,
             "stones": _kind_stones, "fabric": _kind_fabric, "text": _kind_text, "plaster": _kind_plaster}


# ------------------------------------------------------------------ image sets
def _load_image(path: Path, non_colour: bool):
    """The file as a Blender image, loaded once per file per session
    (check_existing); sRGB for 8/16-bit colour maps, linear for EXR."""
    bpy = _bpy()
    img = bpy.data.images.load(str(path), check_existing=True)
    if non_colour:
        img.colorspace_settings.name = "Non-Color"
    else:
        img.colorspace_settings.name = "Linear Rec.709" if path.suffix.lower() == ".exr" else "sRGB"
    return img


def _image_map(g: _Graph, path: Path, vector, non_colour: bool):
    return g.node("ShaderNodeTexImage", image=_load_image(Path(path), non_colour), interpolation="Linear",
                  projection="FLAT", extension="REPEAT", inputs={"Vector": vector})


def _kind_image(g, f, rng, size_m, texture_set):
    """A texture set projected in metres: the image spans a seeded 0.3-2 m
    (at most 4 x the object), shifted by a seeded offset; the normal map goes
    from the set's tangent space to world space through the projection's
    frame (green flipped for DirectX maps). Every ray sees the image: its
    lookups cost little, and the bounce light keeps the image's colours."""
    span_m = min(math.exp(rng.uniform(math.log(0.3), math.log(2.0))), 4.0 * size_m)
    offset = (*rng.uniform(0.0, 1.0, 2), 0.0)
    vector = g.node("ShaderNodeMapping", {"Vector": f.uvw, "Location": offset,
                                          "Scale": (1 / span_m, 1 / span_m, 1.0)}, vector_type="POINT").outputs[0]
    colour = _image_map(g, texture_set.colour, vector, False).outputs["Color"]
    grain = _fine(g, f.uvw, rng, min(size_m, span_m / 8.0, 0.05))
    g.set(g.bsdf.inputs["Base Color"], _mottle(g, colour, grain, rng.uniform(0.04, 0.1)))
    if texture_set.roughness is not None:
        g.set(g.bsdf.inputs["Roughness"], _image_map(g, texture_set.roughness, vector, True).outputs["Color"])
    else:
        g.set(g.bsdf.inputs["Roughness"], g.remap(grain, 0.0, 1.0, *sorted(rng.uniform(0.4, 0.95, 2))))
    if texture_set.normal is not None:
        g.set(g.bsdf.inputs["Normal"], _world_normal(g, f, texture_set, vector))
    else:
        g.set(g.bsdf.inputs["Normal"], g.node("ShaderNodeBump", {"Height": grain, "Distance": 0.001})
              .outputs["Normal"])


def _world_normal(g: _Graph, f: _Frame, texture_set, vector):
    """The set's tangent-space normal map (Non-Color) as a world-space normal:
    n = r' T + g' B + b' N with the projection's tangent T, bitangent B and
    the face normal N (r' = 2 r - 1, ...; DirectX maps: g' = 1 - 2 g), fed to
    a Normal Map node in world space."""
    rgb = g.node("ShaderNodeSeparateColor", {"Color": _image_map(g, texture_set.normal, vector, True)
                                             .outputs["Color"]}).outputs
    flip = texture_set.normal_convention == "dx"

    def decode(channel, scale, offset):
        out = g.math("MULTIPLY_ADD", channel, scale)
        out.node.inputs[2].default_value = offset
        return out

    r = decode(rgb["Red"], 2.0, -1.0)
    gr = decode(rgb["Green"], -2.0 if flip else 2.0, 1.0 if flip else -1.0)
    b = decode(rgb["Blue"], 2.0, -1.0)
    world = g.vmath("ADD", g.vmath("ADD", g.vmath("SCALE", f.tangent, scale=r),
                                   g.vmath("SCALE", f.bitangent, scale=gr)), g.vmath("SCALE", f.normal, scale=b))
    encoded = g.vmath("MULTIPLY_ADD", world, (0.5, 0.5, 0.5))
    encoded.node.inputs[2].default_value = (0.5, 0.5, 0.5)
    return g.node("ShaderNodeNormalMap", {"Color": encoded, "Strength": 1.0}, space="WORLD").outputs["Normal"]


# ------------------------------------------------------------------ the entry point
def _check(kind, textures, image_share, size_m) -> None:
    from dcdi_core.errors import InputRangeError
    if kind is not None and kind not in KINDS + ("image",):
        raise InputRangeError("kind", kind, ", ".join(KINDS) + ", image (with textures) or None")
    if kind == "image" and textures is None:
        raise InputRangeError("kind", kind, "'image' only with a texture library (textures=...)")
    if not (0.0 <= image_share <= 1.0):
        raise InputRangeError("image_share", image_share, "0 to 1 (the probability of an image set)")
    if not (math.isfinite(size_m) and size_m > 0):
        raise InputRangeError("size_m", size_m, "> 0 metres (the object's size), finite")


def surface_material(name: str, rng, *, kind: str | None = None, textures=None, image_share: float = 0.5,
                     size_m: float = 1.0):
    """A Principled BSDF material of ``kind`` (one of KINDS, "image", or None:
    drawn with ``rng``: an image set of ``textures`` with probability
    ``image_share`` when a TextureLibrary is given, else a kind of KINDS)
    for an object ``size_m`` metres across. Returns (material, record), the
    record JSON-able: {"kind": kind} or {"kind": "image", "set": set name}.
    The same ``rng`` state gives the same node values."""
    _check(kind, textures, image_share, size_m)
    if kind is None:
        use_image = textures is not None and rng.random() < image_share
        kind = "image" if use_image else str(KINDS[int(rng.integers(len(KINDS)))])
    mat = _bpy().data.materials.new(name)
    g = _Graph(mat)
    frame = _Frame(g, rng.uniform(-50.0, 50.0, 3))
    if kind == "image":
        chosen = textures.pick(rng)
        _kind_image(g, frame, rng, size_m, chosen)
        return mat, {"kind": "image", "set": chosen.name}
    _BUILDERS[kind](g, frame, rng, size_m)
    return mat, {"kind": kind}

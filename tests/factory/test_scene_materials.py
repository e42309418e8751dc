"""scenes.materials with the pip bpy module: every kind builds, seeds repeat, image sets and their maps."""
import math

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from dcdi_core.dataset.textures import TextureLibrary  # noqa: E402
from dcdi_core.errors import InputRangeError  # noqa: E402
from dcdi_core.io.images import write_image  # noqa: E402
from scenes.materials import KINDS, octaves, surface_material  # noqa: E402

_SKIP = {"location", "location_absolute", "width", "height", "select", "hide", "mute", "name", "label",
         "show_options", "show_preview", "show_texture", "use_custom_color", "color", "width_hidden", "parent",
         "warning_propagation", "color_tag", "bl_width_default", "bl_width_min", "bl_width_max",
         "bl_height_default", "bl_height_min", "bl_height_max", "bl_icon", "bl_static_type", "bl_idname",
         "bl_label", "bl_description"}


@pytest.fixture(autouse=True)
def empty_scene():
    bpy.ops.wm.read_factory_settings(use_empty=True)


def _value(v):
    if isinstance(v, float):
        return round(v, 9)
    if hasattr(v, "__len__") and not isinstance(v, str):
        return tuple(round(float(x), 9) for x in v)
    return getattr(v, "filepath", v)


def signature(mat) -> list:
    """Every node's type, settings, unlinked input values and ramp stops, and every link."""
    out = []
    for n in sorted(mat.node_tree.nodes, key=lambda n: n.name):
        props = {p.identifier: _value(getattr(n, p.identifier)) for p in n.bl_rna.properties
                 if p.identifier not in _SKIP and (p.type in ("ENUM", "FLOAT", "INT", "BOOLEAN")
                                                   or p.identifier == "image")}
        inputs = [(s.identifier, _value(s.default_value)) for s in n.inputs
                  if not s.is_linked and hasattr(s, "default_value")]
        ramp = [(e.position, tuple(e.color)) for e in n.color_ramp.elements] if hasattr(n, "color_ramp") else []
        out.append((n.bl_idname, n.name, sorted(props.items()), inputs, ramp))
    out += sorted((lk.from_node.name, lk.from_socket.identifier, lk.to_node.name, lk.to_socket.identifier)
                  for lk in mat.node_tree.links)
    return out


def _nodes(mat, kind):
    return [n for n in mat.node_tree.nodes if n.bl_idname == kind]


def _camera_bsdf(mat):
    """The BSDF camera rays see: the Mix Shader's second input, its factor
    'Is Camera Ray'; image sets (cheap lookups) have one BSDF for all rays."""
    out = _nodes(mat, "ShaderNodeOutputMaterial")[0]
    mix = out.inputs["Surface"].links[0].from_node
    if _nodes(mat, "ShaderNodeTexImage"):
        assert mix.bl_idname == "ShaderNodeBsdfPrincipled"
        return mix
    assert mix.bl_idname == "ShaderNodeMixShader"
    assert mix.inputs[0].links[0].from_socket.name == "Is Camera Ray"
    return mix.inputs[2].links[0].from_node


def _bsdf_input_from(mat, socket):
    bsdf = _camera_bsdf(mat)
    links = bsdf.inputs[socket].links
    return links[0].from_node if links else None


def _colours(mat) -> set:
    """Distinct colours the material holds: ramp stops and unlinked colour inputs (not black, white, grey 0.5)."""
    found = set()
    for n in mat.node_tree.nodes:
        if hasattr(n, "color_ramp"):
            found |= {tuple(round(c, 4) for c in e.color[:3]) for e in n.color_ramp.elements}
        for s in n.inputs:
            if s.type == "RGBA" and not s.is_linked and n.bl_idname != "ShaderNodeBsdfPrincipled":
                found.add(tuple(round(c, 4) for c in s.default_value[:3]))
    return found - {(0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (0.5, 0.5, 0.5)}


@pytest.mark.parametrize("kind", KINDS)
def test_every_kind_builds_with_colours_bump_and_roughness(kind):
    mat, record = surface_material(f"m-{kind}", np.random.default_rng(1), kind=kind, size_m=0.6)
    assert record == {"kind": kind}
    assert _bsdf_input_from(mat, "Base Color") is not None
    # other rays: a plain BSDF of one colour within the palette's range
    out = _nodes(mat, "ShaderNodeOutputMaterial")[0]
    plain = out.inputs["Surface"].links[0].from_node.inputs[1].links[0].from_node
    assert not plain.inputs["Base Color"].is_linked and 0.0 < max(plain.inputs["Base Color"].default_value[:3]) < 0.9
    assert _bsdf_input_from(mat, "Roughness") is not None             # varies over the surface
    bump = _bsdf_input_from(mat, "Normal")
    assert bump is not None and bump.bl_idname == "ShaderNodeBump" and bump.inputs["Height"].is_linked
    assert len(_colours(mat)) >= 4, _colours(mat)                      # not a two-colour ramp
    # fine detail: a noise reaching FINEST_M, or (text) glyph cells of a few mm
    assert _nodes(mat, "ShaderNodeTexNoise")
    assert any(n.bl_idname.startswith("ShaderNodeTex") and n.bl_idname != "ShaderNodeTexNoise"
               for n in mat.node_tree.nodes) or kind in ("noise", "plaster")


def test_fine_detail_reaches_a_few_millimetres():
    mat, _ = surface_material("m", np.random.default_rng(3), kind="noise", size_m=2.0)
    finest = min(1.0 / n.inputs["Scale"].default_value / 2.0 ** n.inputs["Detail"].default_value
                 for n in _nodes(mat, "ShaderNodeTexNoise") if not n.inputs["Detail"].is_linked)
    assert finest <= 0.0025
    assert octaves(1.0, 0.002) == pytest.approx(math.log2(500))


@pytest.mark.parametrize("kind", KINDS)
def test_same_seed_same_nodes_other_seed_other_nodes(kind):
    a = signature(surface_material("a", np.random.default_rng(7), kind=kind, size_m=1.3)[0])
    b = signature(surface_material("b", np.random.default_rng(7), kind=kind, size_m=1.3)[0])
    c = signature(surface_material("c", np.random.default_rng(8), kind=kind, size_m=1.3)[0])
    assert a == b
    assert a != c


def test_kind_drawn_from_kinds():
    rng = np.random.default_rng(0)
    kinds = {surface_material(f"m{i}", rng)[1]["kind"] for i in range(40)}
    assert kinds <= set(KINDS) and len(kinds) >= 6


def _two_pngs(folder):
    rng = np.random.default_rng(0)
    for name in ("pebbles.png", "poster.png"):
        write_image(folder / name, rng.uniform(0.0, 1.0, (8, 8, 3)).astype(np.float32))
    return TextureLibrary.from_folder(folder)


def test_texture_library_sets_are_all_used_and_loaded_once(tmp_path):
    lib = _two_pngs(tmp_path)
    rng = np.random.default_rng(2)
    records = [surface_material(f"m{i}", rng, textures=lib, image_share=1.0)[1] for i in range(20)]
    assert {r["kind"] for r in records} == {"image"}
    assert {r["set"] for r in records} == {"pebbles", "poster"}
    assert len(bpy.data.images) == 2                                   # once per file, not per material
    assert {img.colorspace_settings.name for img in bpy.data.images} == {"sRGB"}
    mixed = [surface_material(f"x{i}", rng, textures=lib, image_share=0.5)[1]["kind"] for i in range(30)]
    assert "image" in mixed and set(mixed) - {"image"}


def test_image_set_same_seed_same_nodes(tmp_path):
    lib = _two_pngs(tmp_path)
    a = signature(surface_material("a", np.random.default_rng(4), textures=lib, image_share=1.0)[0])
    b = signature(surface_material("b", np.random.default_rng(4), textures=lib, image_share=1.0)[0])
    assert a == b


def test_normal_and_roughness_maps(tmp_path):
    rng = np.random.default_rng(0)
    for name in ("brick_Color.png", "brick_NormalDX.png", "brick_Roughness.png", "wall.exr"):
        write_image(tmp_path / name, rng.uniform(0.0, 1.0, (8, 8, 3)).astype(np.float32))
    lib = TextureLibrary.from_folder(tmp_path)
    brick = next(s for s in lib.sets if s.normal is not None)
    assert brick.normal_convention == "dx"
    lib_brick = TextureLibrary(folder=lib.folder, sets=(brick,))
    mat, record = surface_material("m", np.random.default_rng(1), kind="image", textures=lib_brick)
    assert record == {"kind": "image", "set": "brick"}
    normal = _bsdf_input_from(mat, "Normal")
    assert normal.bl_idname == "ShaderNodeNormalMap" and normal.space == "WORLD"
    roughness = _bsdf_input_from(mat, "Roughness")
    assert roughness.bl_idname == "ShaderNodeTexImage" and roughness.image.colorspace_settings.name == "Non-Color"
    images = {n.image.filepath: n.image.colorspace_settings.name for n in _nodes(mat, "ShaderNodeTexImage")}
    assert images == {str(brick.colour): "sRGB", str(brick.normal): "Non-Color", str(brick.roughness): "Non-Color"}
    # DirectX maps: green flipped (decoded as 1 - 2 g instead of 2 g - 1)
    green = next(lk.to_node for n in _nodes(mat, "ShaderNodeSeparateColor") for lk in n.outputs["Green"].links)
    assert green.operation == "MULTIPLY_ADD" and green.inputs[1].default_value == -2.0
    # a colour-only set: no normal map node, the grain's bump instead
    wall = next(s for s in lib.sets if s.name == "wall")
    mat, _ = surface_material("w", np.random.default_rng(1), kind="image",
                              textures=TextureLibrary(folder=lib.folder, sets=(wall,)))
    assert not _nodes(mat, "ShaderNodeNormalMap") and _bsdf_input_from(mat, "Normal").bl_idname == "ShaderNodeBump"
    assert _nodes(mat, "ShaderNodeTexImage")[0].image.colorspace_settings.name == "Linear Rec.709"


@pytest.mark.parametrize("kwargs, name", [({"kind": "marble"}, "kind"), ({"kind": "image"}, "kind"),
                                          ({"image_share": 1.5}, "image_share"), ({"size_m": 0.0}, "size_m"),
                                          ({"size_m": math.nan}, "size_m")])
def test_bad_arguments_refused_before_any_material(kwargs, name):
    with pytest.raises(InputRangeError, match=name):
        surface_material("m", np.random.default_rng(0), **kwargs)
    assert len(bpy.data.materials) == 0


def test_material_texture_tool_renders_a_tiny_frame(capsys):
    from blender_addon.tools.material_texture import main
    assert main(["--kind", "bricks", "--seeds", "1", "--resolution", "12", "16"]) == 0
    row = next(line for line in capsys.readouterr().out.splitlines() if line.startswith("| bricks |"))
    hf = float(row.split("|")[2].strip().rstrip(" %"))
    assert 0.0 < hf <= 100.0

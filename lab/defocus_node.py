"""Blender's compositor Defocus node (Z buffer) on an RGB-D image, headless and timed.

    python -m lab.defocus_node --input rgbd.npz --lens 6p --focus 1.2 --out out.npz \\
        [--json timings.json] [--repeat 2] [--threads N]
    blender --background --python lab/defocus_node.py -- --input ... (same options)

What a Blender user reaches for to add depth of field after rendering: the
compositor's Defocus node fed with the image and its Z pass, the scene
camera's focal length, sensor and focus distance, the node's f-stop. The
camera maths is the lab's (``lab.thin_lens.NodeDefocus``, from dcdi_core's
optics: focal length and F-number from the lens's paraxial first order, Z
from its front principal plane, sensor = the image's width on the lens's
sensor, blur_max the largest blur radius the depth map needs); this tool
only copies those values into Blender and runs the compositor (circular
bokeh, full quality: Blender 5 has no preview mode).

Input: ``.npz`` with ``image`` (H, W, 3) linear float and ``depth`` (H, W)
metres from the lens's first vertex (docs/design.md: inf or 1e10 = infinity; NaN,
0, negative = invalid, left sharp); or ``--input`` an image (.npy, .exr) with
``--depth`` its depth map (.npy, .exr: the first channel). Output: ``.npz``
(``image``, float32 (H, W, 3)) or ``.exr`` (32-bit float RGBA), written to
a temporary name and renamed.

Timing (printed and in ``--json``; wall and CPU seconds): Blender's start-up (``import bpy``; 0
under the blender binary, whose start precedes this script: the caller
times the whole process), the set-up (pixels into Blender images, the node
tree), each composite (``bpy.ops.render.render``: the tree has no Render
Layers node, so no scene is rendered: this is the node's own time), and the
write; with the process's peak RSS.
"""
from __future__ import annotations

import time

T_START = time.perf_counter()

import argparse  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import resource  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

MIN_BLENDER = (5, 0, 0)       # scene.compositing_node_group, Group Output as the compositor's output


def _import_bpy():
    try:
        import bpy
    except ImportError:
        raise SystemExit("defocus_node: no bpy module: run it with Blender (blender --background --python "
                         "lab/defocus_node.py -- ...) or install the pip bpy module "
                         "(see requirements.txt)")
    if tuple(bpy.app.version) < MIN_BLENDER:
        raise SystemExit(f"defocus_node: Blender {bpy.app.version_string} is too old: its compositor API "
                         f"differs; this tool needs Blender >= {'.'.join(map(str, MIN_BLENDER))}")
    return bpy


bpy = _import_bpy()
T_BPY = time.perf_counter()

import numpy as np  # noqa: E402

if __package__ in (None, ""):          # run as a file by `blender --python`
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def parse(argv):
    p = argparse.ArgumentParser(prog="python -m lab.defocus_node",
                                description=__doc__.split("\n")[0])
    p.add_argument("--input", required=True, help=".npz (image, depth) or an image .npy / .exr (with --depth)")
    p.add_argument("--depth", help="depth map .npy / .exr (metres from the lens's first vertex) for an image input")
    p.add_argument("--lens", default="6p", help="lens id or .toml (default 6p)")
    p.add_argument("--focus", type=float, required=True, help="focus distance, metres from the lens's first vertex")
    p.add_argument("--out", required=True, help="result .npz or .exr")
    p.add_argument("--json", help="timings and settings as JSON")
    p.add_argument("--repeat", type=int, default=1, help="composites to time (>= 1; the best is reported)")
    p.add_argument("--threads", type=int, default=0, help="Blender threads (0: all cores, Blender's default)")
    a = p.parse_args(argv)
    if a.repeat < 1:
        p.error(f"--repeat {a.repeat}: must be >= 1")
    if a.threads < 0:
        p.error(f"--threads {a.threads}: must be >= 0 (0: all cores)")
    if not os.path.isfile(a.input):
        p.error(f"--input {a.input}: no such file")
    if Path(a.input).suffix != ".npz" and not a.depth:
        p.error(f"--input {a.input}: an image needs --depth (or give an .npz with image and depth)")
    if Path(a.out).suffix not in (".npz", ".exr"):
        p.error(f"--out {a.out}: must end in .npz or .exr")
    if a.json and Path(a.json).suffix != ".json":
        p.error(f"--json {a.json}: must end in .json")
    return a


def _read_exr(path: str) -> np.ndarray:
    """(H, W, 4) float32, top row first, through Blender's image API."""
    im = bpy.data.images.load(path, check_existing=False)
    try:
        w, h = im.size
        px = np.empty(w * h * 4, np.float32)
        im.pixels.foreach_get(px)
        return px.reshape(h, w, 4)[::-1]
    finally:
        bpy.data.images.remove(im)


def read_rgbd(path: str, depth_path: str | None) -> tuple[np.ndarray, np.ndarray]:
    """(image (H, W, 3) float32, depth (H, W) float64); shapes and values checked."""
    if Path(path).suffix == ".npz":
        with np.load(path, allow_pickle=False) as z:
            missing = {"image", "depth"} - set(z.files)
            if missing:
                raise SystemExit(f"defocus_node: {path}: no array {', '.join(sorted(missing))} (it holds {z.files})")
            img, depth = z["image"], z["depth"]
    else:
        def one(p):
            return np.load(p, allow_pickle=False) if Path(p).suffix == ".npy" else _read_exr(p)
        img, depth = one(path), one(depth_path)
        depth = depth if depth.ndim == 2 else depth[..., 0]
    img = np.asarray(img, np.float32)
    if img.ndim != 3 or img.shape[2] not in (3, 4):
        raise SystemExit(f"defocus_node: {path}: image shape {img.shape}; allowed (H, W, 3)")
    img = img[..., :3]
    depth = np.asarray(depth, np.float64)
    if depth.shape != img.shape[:2]:
        raise SystemExit(f"defocus_node: depth map shape {depth.shape}; allowed {img.shape[:2]}, the image's")
    if not np.isfinite(img).all():
        raise SystemExit(f"defocus_node: {path}: the image holds non-finite values; allowed: finite linear RGB")
    return img, depth


def _float_image(name: str, pixels: np.ndarray, colorspace: str):
    """A float RGBA Blender image holding ``pixels`` (H, W, 3), top row first.
    The colour space is set before the pixels: setting it afterwards
    regenerates the (generated) image and drops them."""
    h, w, _ = pixels.shape
    im = bpy.data.images.new(name, w, h, alpha=True, float_buffer=True)
    im.colorspace_settings.name = colorspace
    rgba = np.ones((h, w, 4), np.float32)
    rgba[..., :3] = pixels
    im.pixels.foreach_set(rgba[::-1].ravel())        # Blender's rows run bottom to top
    return im


def build_scene(img: np.ndarray, z: np.ndarray, settings: dict, threads: int):
    """An empty scene: the camera of ``settings['camera']``, a compositor
    Image -> Defocus (Z from a second image's red channel) -> output."""
    # not read_factory_settings: it re-registers every add-on (factory.batch.empty_scene says why)
    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    scene = bpy.context.scene
    h, w = img.shape[:2]
    r = scene.render
    r.resolution_x, r.resolution_y, r.resolution_percentage = w, h, 100
    r.threads_mode = "FIXED" if threads else "AUTO"
    if threads:
        r.threads = threads
    r.compositor_device = "CPU"
    scene.view_settings.view_transform = "Standard"
    cam = settings["camera"]
    data = bpy.data.cameras.new("Defocus camera")
    data.lens = cam["lens"]
    data.sensor_fit = cam["sensor_fit"]
    data.sensor_width, data.sensor_height = cam["sensor_width"], cam["sensor_height"]
    data.dof.focus_distance = cam["dof_focus_distance"]
    obj = bpy.data.objects.new("Defocus camera", data)
    scene.collection.objects.link(obj)
    scene.camera = obj
    # Blender clamps what it cannot hold: read back, so a clamp is an error, not another blur
    for key, got in (("lens", data.lens), ("sensor_width", data.sensor_width),
                     ("sensor_height", data.sensor_height), ("dof_focus_distance", data.dof.focus_distance)):
        if abs(got - cam[key]) > 1e-5 * max(1.0, abs(cam[key])):
            raise SystemExit(f"defocus_node: Blender's camera {key} became {got} (asked {cam[key]})")
    tree = bpy.data.node_groups.new("Defocus", "CompositorNodeTree")
    scene.compositing_node_group = tree
    tree.interface.new_socket("Image", in_out="OUTPUT", socket_type="NodeSocketColor")
    colour = tree.nodes.new("CompositorNodeImage")
    colour.image = _float_image("rgb", img, "Linear Rec.709")
    depth = tree.nodes.new("CompositorNodeImage")
    depth.image = _float_image("z", np.repeat(z[..., None], 3, axis=-1), "Non-Color")
    split = tree.nodes.new("CompositorNodeSeparateColor")
    node = tree.nodes.new("CompositorNodeDefocus")
    for key, value in settings["node"].items():
        setattr(node, key, value)
        got = getattr(node, key)
        if got != value and not (isinstance(value, float) and abs(got - value) <= 1e-5 * max(1.0, abs(value))):
            raise SystemExit(f"defocus_node: the Defocus node's {key} became {got} (asked {value})")
    out = tree.nodes.new("NodeGroupOutput")
    tree.links.new(colour.outputs["Image"], node.inputs["Image"])
    tree.links.new(depth.outputs["Image"], split.inputs["Image"])
    tree.links.new(split.outputs["Red"], node.inputs["Z"])
    tree.links.new(node.outputs["Image"], out.inputs[0])
    im = r.image_settings
    im.file_format = "OPEN_EXR"
    im.color_depth = "32"
    im.exr_codec = "NONE"
    im.color_mode = "RGBA"
    return scene


def write_result(scene, out: Path) -> np.ndarray:
    """Save the composite (an .exr as Blender writes it, or an .npz of its
    RGB) to a temporary name, then rename; return it (H, W, 3) float32."""
    import tempfile

    from dcdi_core.atomic import atomic_path
    from dcdi_core.io.rawexr import read_exr_channels

    def save(path) -> np.ndarray:
        bpy.data.images["Render Result"].save_render(str(path), scene=scene)
        ch = read_exr_channels(path)
        return np.stack([ch["R"], ch["G"], ch["B"]], -1).astype(np.float32)

    if out.suffix == ".exr":
        with atomic_path(out) as tmp:
            return save(tmp)
    with tempfile.TemporaryDirectory() as d:
        img = save(Path(d) / "result.exr")
    with atomic_path(out) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, image=img)
    return img


def _rss_mib() -> float:
    """The process's resident set now, MiB (Linux /proc; else its peak so far)."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2 ** 20
    except (OSError, ValueError, IndexError):
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def run(argv=None) -> int:
    argv = sys.argv[sys.argv.index("--") + 1:] if argv is None and "--" in sys.argv else argv
    a = parse(sys.argv[1:] if argv is None else argv)
    from dcdi_core.optics.lens import load_lens
    from lab.thin_lens import NodeDefocus

    t0 = time.perf_counter()
    img, depth = read_rgbd(a.input, a.depth)
    lens = load_lens(a.lens)
    thin = NodeDefocus.for_lens(lens, img.shape[0], img.shape[1], a.focus)
    settings = thin.blender_settings(depth)
    scene = build_scene(img, thin.node_z(depth), settings, a.threads)
    t_setup = time.perf_counter() - t0
    rss_before = _rss_mib()
    times, cpu = [], []
    for _ in range(a.repeat):
        t, c = time.perf_counter(), time.process_time()
        bpy.ops.render.render()
        times.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    t = time.perf_counter()
    result = write_result(scene, Path(a.out))
    t_write = time.perf_counter() - t
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024          # KiB on Linux
    record = {"blender": bpy.app.version_string, "lens": lens.id, "focus_m": a.focus,
              "height": img.shape[0], "width": img.shape[1], "settings": settings,
              "thin_lens": {"focal_length_mm": thin.focal_length_mm, "f_number": thin.f_number,
                            "principal_plane_mm": thin.principal_plane_mm, "pixel_pitch_mm": thin.pixel_pitch_mm},
              "threads": a.threads or os.cpu_count(), "startup_s": T_BPY - T_START, "setup_s": t_setup,
              "composite_s": times, "composite_cpu_s": cpu, "write_s": t_write, "peak_rss_mib": rss, "rss_before_composite_mib": rss_before,
              "finite": bool(np.isfinite(result).all())}
    print(f"defocus_node: Blender {record['blender']}, {img.shape[0]} x {img.shape[1]}, {lens.id} thin lens "
          f"f {thin.focal_length_mm:.2f} mm F/{thin.f_number:.3f} focused at {a.focus:g} m, blur_max "
          f"{settings['node']['blur_max']:.2f} px; start-up {record['startup_s']:.2f} s, set-up {t_setup:.2f} s, "
          f"composite {min(times):.2f} s (best of {len(times)}; {cpu[times.index(min(times))]:.2f} CPU s), write {t_write:.2f} s, peak RSS {rss:.0f} MiB")
    if a.json:
        from dcdi_core.atomic import write_text
        write_text(a.json, json.dumps(record, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(run())

"""The scene's own compositor on the frame through the lens.

Blender composites a frame before an add-on sees its pixels, so Lens in
Renders puts a compositor of its own in place of the scene's for the
render (``render_hook``): it writes the passes to a file. Where the scene's
compositor changes the picture (:func:`user_tree`: any node but Render
Layers, Group Output, Viewer, Reroute and Frame, a File Output included),
it is kept, applied after the lens:

- at the render's start (:func:`prepare`), a copy of the scene's node
  tree, each Render Layers node replaced by one Image node for each pass
  it feeds (File Output folders made absolute), is written to a .blend,
  and a background Blender (the helper) starts, its start overlapping the
  render;
- for each frame (:meth:`Compositor.composite`), the helper gets the
  passes the tree reads (the lens on the Combined pass of the scene's own
  layers, every other pass as rendered), fills the Image nodes with them
  and renders its scene: a scene whose compositor has no Render Layers
  node renders nothing and only composites (0.1-0.3 s at 1920 x 1080),
  written as a 32-bit EXR, which is the frame.

No bpy at module level: the helper's side (:func:`serve`) runs this file
as the helper Blender's script.
"""
from __future__ import annotations

import json
import os
import queue
import subprocess
import sys
import threading
from dataclasses import dataclass, field
from pathlib import Path

MARK = "DCDI-COMPOSITOR "
READY_S = 60.0           # the helper's start (Blender's, 0.7-1.6 s here; slower on a busy machine)
FRAME_S = 120.0          # one frame's compositing (the scene's own nodes: a large blur can take long)
# nodes that pass the render through unchanged: a tree of only these is no compositor to keep
PASS_THROUGH = {"CompositorNodeRLayers", "NodeGroupOutput", "CompositorNodeViewer", "NodeReroute", "NodeFrame"}
# a Render Layers output's socket type -> the File Output item that writes it
ITEM_TYPE = {"RGBA": "RGBA", "VALUE": "FLOAT", "VECTOR": "VECTOR"}
PLACEHOLDER = "dcdi-pass"


@dataclass
class Source:
    """What the tree reads from one view layer: the layer's passes by name."""
    scene: str
    layer: str
    passes: dict = field(default_factory=dict)          # pass name: socket type (RGBA, VALUE, VECTOR)
    images: dict = field(default_factory=dict)          # pass name: the placeholder image's name in the copy


# ------------------------------------------------------------------ the user's Blender's side
def user_tree(scene):
    """The scene's compositor where it changes the frame, else None."""
    tree = getattr(scene, "compositing_node_group", None)
    if not scene.render.use_compositing or tree is None:
        return None
    if all(n.bl_idname in PASS_THROUGH or n.mute for n in tree.nodes):
        return None
    return tree


def nested_render_layers(tree, seen=None) -> str | None:
    """The name of a node group inside ``tree`` that reads Render Layers
    (which the copy cannot feed), or None."""
    seen = set() if seen is None else seen
    for node in tree.nodes:
        group = getattr(node, "node_tree", None)
        if group is None or group.name in seen:
            continue
        seen.add(group.name)
        if any(n.bl_idname == "CompositorNodeRLayers" for n in group.nodes) or nested_render_layers(group, seen):
            return group.name
    return None


def sources(tree, scene) -> list[Source]:
    """The view layers ``tree``'s Render Layers nodes read, each with the
    passes linked from it."""
    out: dict[tuple, Source] = {}
    for node in tree.nodes:
        if node.bl_idname != "CompositorNodeRLayers" or node.mute:
            continue
        src = out.setdefault(((node.scene or scene).name, node.layer),
                             Source((node.scene or scene).name, node.layer))
        for sock in node.outputs:
            if sock.is_linked and sock.enabled and sock.type in ITEM_TYPE:
                src.passes[sock.name] = sock.type
    return list(out.values())


def prepare(scene, tree, folder: Path) -> tuple[Path, list[Source]]:
    """Write the copy of ``tree`` the helper composites (Render Layers
    replaced by placeholder Image nodes) to ``folder``/compositor.blend;
    the copy and its placeholders are removed from this Blender again.
    Returns the file and the sources the placeholders stand for."""
    import bpy
    found = sources(tree, scene)
    by_key = {(s.scene, s.layer): s for s in found}
    copy = tree.copy()
    made = []
    try:
        for node in list(copy.nodes):
            if node.bl_idname == "CompositorNodeOutputFile":
                node.directory = bpy.path.abspath(node.directory)     # the copy's file lives elsewhere
            if node.bl_idname != "CompositorNodeRLayers":
                continue
            if node.mute:
                copy.nodes.remove(node)
                continue
            src = by_key[((node.scene or scene).name, node.layer)]
            for sock in node.outputs:
                if sock.name not in src.passes or not sock.is_linked:
                    continue
                if sock.name not in src.images:
                    img = bpy.data.images.new(f"{PLACEHOLDER} {len(made)}", 1, 1, alpha=True, float_buffer=True)
                    made.append(img)
                    src.images[sock.name] = img.name
                image_node = copy.nodes.new("CompositorNodeImage")
                image_node.image = bpy.data.images[src.images[sock.name]]
                image_node.location = node.location
                for link in list(sock.links):
                    copy.links.new(image_node.outputs["Image"], link.to_socket)
            copy.nodes.remove(node)
        path = folder / "compositor.blend"
        bpy.data.libraries.write(str(path), {copy}, path_remap="ABSOLUTE", compress=False)
        names = {"group": copy.name}
    finally:
        bpy.data.node_groups.remove(copy)
        for img in made:
            bpy.data.images.remove(img)
    (folder / "compositor.json").write_text(json.dumps(names))
    return path, found


def helper_command(script: str) -> list[str]:
    """How to run ``script`` in a background Blender: Blender's binary, or
    (the pip ``bpy`` module, which has none) this Python."""
    import bpy
    binary = getattr(bpy.app, "binary_path", "")
    if binary and os.path.exists(binary):
        return [binary, "-b", "--factory-startup", "--python-exit-code", "1", "--python", script]
    return [sys.executable, script]


class Compositor:
    """The scene's compositor for one render through the lens: the helper
    Blender and what it composites."""

    def __init__(self, blend: Path, group: str, found: list[Source], settings: dict):
        self.blend, self.group, self.sources, self.settings = blend, group, found, settings
        self.folder = blend.parent
        self.answers: queue.Queue = queue.Queue()
        self.count = 0
        env = dict(os.environ, DCDI_COMPOSITOR=json.dumps({"blend": str(blend), "group": group, **settings}))
        self.proc = subprocess.Popen(helper_command(str(Path(__file__).resolve())), stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
                                     encoding="utf-8", errors="replace", bufsize=1, env=env)
        threading.Thread(target=self._read, name="dcdi-compositor-reader", daemon=True).start()
        self.ready = False

    @classmethod
    def start(cls, scene, tree, folder: Path) -> Compositor:
        """Write the tree's copy and start the helper (it opens the copy while the render runs)."""
        blend, found = prepare(scene, tree, folder)
        r = scene.render
        settings = {"precision": getattr(r, "compositor_precision", "AUTO"), "fps": r.fps, "fps_base": r.fps_base,
                    "frame_start": scene.frame_start, "frame_end": scene.frame_end}
        return cls(blend, json.loads((folder / "compositor.json").read_text())["group"], found, settings)

    def _read(self) -> None:
        for line in self.proc.stdout:
            if line.startswith(MARK):
                try:
                    self.answers.put(json.loads(line[len(MARK):]))
                except ValueError:
                    continue
        self.answers.put({"ended": self.proc.wait()})

    def _answer(self, timeout: float) -> dict:
        try:
            msg = self.answers.get(timeout=timeout)
        except queue.Empty:
            raise RuntimeError(f"the compositor's Blender did not answer within {timeout:.0f} s") from None
        if "ended" in msg:
            raise RuntimeError(f"the compositor's Blender ended (exit {msg['ended']})")
        if "error" in msg:
            raise RuntimeError(f"the scene's compositor failed: {msg['error']}")
        return msg

    def composite(self, frame: int, passes: dict):
        """The composited frame, (H, W, 4) float32 linear RGBA, rows top to
        bottom, of ``passes`` ({(scene, layer): {pass name: (H, W, k)
        array}}, every pass of :attr:`sources`)."""
        import numpy as np
        if not self.ready:
            self._answer(READY_S)
            self.ready = True
        self.count += 1
        feed = {}
        for src in self.sources:
            for name, image in src.images.items():
                path = self.folder / f"pass-{len(feed)}.npy"
                np.save(path, np.ascontiguousarray(passes[(src.scene, src.layer)][name], np.float32))
                feed[image] = str(path)
        h, w = next(a for layer in passes.values() for a in layer.values()).shape[:2]
        out = self.folder / f"composite-{self.count}.exr"
        self.proc.stdin.write(json.dumps({"id": self.count, "frame": frame, "w": w, "h": h, "images": feed,
                                          "out": str(out)}) + "\n")
        self.proc.stdin.flush()
        self._answer(FRAME_S)
        from dcdi_core import app
        try:
            ch = app.rawexr.read_exr_channels(out)
        finally:
            out.unlink(missing_ok=True)
            for p in feed.values():
                Path(p).unlink(missing_ok=True)
        if not {"R", "G", "B"} <= set(ch):
            raise RuntimeError(f"the compositor's frame has no colour (channels: {sorted(ch)[:8]})")
        alpha = ch.get("A", np.ones_like(ch["R"]))
        return np.stack([ch["R"], ch["G"], ch["B"], alpha], axis=-1).astype(np.float32)

    def stop(self) -> None:
        try:
            self.proc.stdin.close()
        except OSError:
            pass
        try:
            self.proc.wait(5)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


def split_passes(channels: dict) -> dict:
    """A multilayer EXR's channels ({"Image.R": (H, W), ...}) as passes
    ({"Image": (H, W, k)}), channels in R G B A / X Y Z W / V order."""
    import numpy as np
    order = {c: i for i, c in enumerate("RGBAXYZWV")}
    grouped: dict[str, list] = {}
    for name in channels:
        stem, _, channel = name.rpartition(".")
        grouped.setdefault(stem, []).append(channel)
    return {stem: np.stack([channels[f"{stem}.{c}"] for c in sorted(cs, key=lambda c: order.get(c, 99))], axis=-1)
            for stem, cs in grouped.items()}


# ------------------------------------------------------------------ the helper's side
def _rgba(array):
    """(H, W, k) -> (H, W, 4) for an image: one channel repeated in RGB, alpha 1 where none."""
    import numpy as np
    h, w, k = array.shape
    out = np.ones((h, w, 4), np.float32)
    if k == 1:
        out[..., :3] = array
    else:
        out[..., :min(k, 4)] = array[..., :4]
    return out


def serve() -> None:
    """The helper's loop: a frame a line until its input ends."""
    import bpy
    import numpy as np
    cfg = json.loads(os.environ["DCDI_COMPOSITOR"])
    scene = bpy.context.scene
    try:
        with bpy.data.libraries.load(cfg["blend"], link=False) as (src, dst):
            dst.node_groups = [cfg["group"]]
        group = dst.node_groups[0]
        r = scene.render
        scene.compositing_node_group = group
        r.use_compositing, r.use_sequencer = True, False
        if hasattr(r, "compositor_precision"):
            r.compositor_precision = cfg["precision"]
        r.fps, r.fps_base = cfg["fps"], cfg["fps_base"]
        scene.frame_start, scene.frame_end = cfg["frame_start"], cfg["frame_end"]
        r.resolution_percentage = 100
        r.image_settings.file_format = "OPEN_EXR"
        r.image_settings.color_depth = "32"
        r.image_settings.color_mode = "RGBA"
        r.use_file_extension = False
    except Exception as e:          # noqa: BLE001 - said to the user's Blender, which goes on without it
        _reply({"error": f"{type(e).__name__}: {e}"})
        return
    _reply({"ready": True})
    for line in sys.stdin:
        try:
            req = json.loads(line)
            r.resolution_x, r.resolution_y = req["w"], req["h"]
            scene.frame_set(req["frame"])
            for name, path in req["images"].items():
                a = _rgba(np.load(path))[::-1]                 # Blender's rows run bottom to top
                img = bpy.data.images[name]
                if tuple(img.size) != (a.shape[1], a.shape[0]):
                    img.scale(a.shape[1], a.shape[0])
                img.pixels.foreach_set(a.ravel())
                img.update()
            r.filepath = req["out"]
            bpy.ops.render.render(write_still=True)
            if not os.path.exists(req["out"]):
                raise RuntimeError("no frame written (does the compositor end in a Group Output?)")
            _reply({"id": req["id"], "out": req["out"]})
        except Exception as e:      # noqa: BLE001 - answered: the user's Blender says it
            _reply({"id": None, "error": f"{type(e).__name__}: {e}"})


def _reply(msg: dict) -> None:
    sys.stdout.write(MARK + json.dumps(msg) + "\n")
    sys.stdout.flush()


if __name__ == "__main__":
    serve()

"""RGB-D sources for DA2T training: all-in-focus images with metric depth.

Every reader gives frames as the project holds them in memory (docs/design.md):
image float32 (H, W, 3) linear light, depth float32 (H, W) planar metres
(NaN invalid, inf infinity), and says which *scene* each frame shows, so
that a split by scene keeps every view of a scene on one side.

Readers (each ``ids()``, ``scene(id)``, ``load(id) -> RGBDFrame``):

``FactoryFolder(root)``
    the dataset factory's output (format: ``dataset.factory_folder``): ids
    from ``manifest.jsonl`` (finished samples only), ``aif/<id>.exr`` and
    ``depth/<id>.exr``; each sample is its own seeded scene. The factory's
    own pre-simulated pairs (``<lens>/aberrated|baseline|sharp``) are read
    by ``pair(id, lens)``.
``RGBDFolder(root)``
    the generic layout::

        images/<id>.exr | .png          linear EXR, or 8/16-bit sRGB PNG
        depth/<id>.exr | .npy | .png     metres (EXR 'Z' or first channel, NPY), or 16-bit PNG in mm (0 invalid)
        scenes.json                      optional {id: scene}; without it each id is its own scene

``NYUv2Labeled(path)``
    NYU Depth v2's ``nyu_depth_v2_labeled.mat`` (MATLAB v7.3, i.e. HDF5;
    read with h5py): ``images`` (N, 3, W, H) uint8 sRGB and ``depths``
    (N, W, H) metres, both stored transposed (MATLAB is column-major);
    ``scenes`` (cell array of names such as 'kitchen_0004') gives the
    scene. 1449 frames of 480 x 640. Get it from the dataset's page at
    cs.nyu.edu (silberman, datasets/nyu_depth_v2).
``Middlebury2014(root)``
    one folder per scene as the 2014 stereo set ships it: ``im0.png``,
    ``disp0.pfm`` (left disparity, px; inf unknown) and ``calib.txt``
    (``cam0=[f 0 cx; 0 f cy; 0 0 1]``, ``doffs``, ``baseline`` in mm).
    Depth Z = baseline f / (d + doffs) (mm, then m). 'Adirondack-perfect'
    and 'Adirondack-imperfect' are one scene, 'Adirondack'. From
    vision.middlebury.edu/stereo/data/scenes2014.
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import ModelError
from ..io.image_file import ImageFileError
from ..io.images import read_depth, read_image, srgb_to_linear
from . import factory_folder as ff
from ..io.jsontext import loads


@dataclass
class RGBDFrame:
    id: str
    scene: str
    image: np.ndarray            # (H, W, 3) float32 linear
    depth: np.ndarray            # (H, W) float32 metres (NaN invalid, inf infinity)
    source: str = ""
    meta: dict = field(default_factory=dict)


class RGBDSource:
    """Base of the readers: ``ids()``, ``scene(id)``, ``load(id)``."""

    name = "rgbd"

    def ids(self) -> list[str]:
        raise NotImplementedError

    def scene(self, id: str) -> str:
        return id

    def load(self, id: str) -> RGBDFrame:
        raise NotImplementedError

    def __len__(self):
        return len(self.ids())

    def frames(self):
        for i in self.ids():
            yield self.load(i)


def _first(folder: Path, stem: str, exts, what: str) -> Path:
    for e in exts:
        p = folder / f"{stem}{e}"
        if p.exists():
            return p
    raise ImageFileError(folder / stem, f"no {what} file ({' or '.join(exts)})")


def read_depth_png_mm(path) -> np.ndarray:
    """A 16-bit PNG of depth in millimetres -> float32 metres (0 -> NaN, invalid)."""
    from ..io.image_file import NO_OPENIMAGEIO, _oiio

    path = Path(path)
    oiio = _oiio()
    if oiio is None:
        raise ImageFileError(path, f"a PNG depth map cannot be read without OpenImageIO: {NO_OPENIMAGEIO}")
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise ImageFileError(path, f"cannot be opened ({oiio.geterror()})")
    try:
        spec = inp.spec()
        if spec.format.basetype != oiio.BASETYPE.UINT16:
            raise ImageFileError(path, f"a depth PNG must be 16-bit (millimetres); this one holds {spec.format}")
        data = np.asarray(inp.read_image(oiio.UINT16))
    finally:
        inp.close()
    if data.ndim == 3:
        data = data[..., 0]
    d = data.astype(np.float32) / 1000.0
    d[data == 0] = np.nan
    return d


def read_any_depth(path) -> np.ndarray:
    """Depth in metres from an EXR, a .npy or a 16-bit PNG in mm."""
    path = Path(path)
    if path.suffix.lower() == ".png":
        return read_depth_png_mm(path)
    return read_depth(path)


class FactoryFolder(RGBDSource):
    """A factory folder (layout and manifest: ``dataset.factory_folder``)."""

    name = "factory"

    def __init__(self, root):
        self.root = Path(root)
        self.layout = ff.FolderLayout(self.root)
        if not self.layout.manifest.exists():
            raise ModelError(f"{self.layout.manifest}: not found (a factory output folder has one; see "
                             "docs/factory.md)")
        self.records = ff.finished_samples(self.root)       # a torn last record: that sample is not finished
        self._ids = sorted(self.records)

    def ids(self):
        return list(self._ids)

    def scene(self, id):
        """The frame's id and its scene seed: two factory folders (other
        dataset seeds) reuse the ids, never the scenes."""
        seed = self.records[id].get("seed")
        return id if seed is None else f"{id}#{seed}"

    def load(self, id):
        img, dep = ff.read_rgbd(self.layout, id)
        return RGBDFrame(id, self.scene(id), img, dep, self.name, {"manifest": self.records[id]})

    def pair(self, id, lens: str) -> dict:
        """The factory's own simulation of ``lens``: aberrated, baseline, sharp (H, W, 3)."""
        return ff.read_lens_images(self.layout, lens, id)


class RGBDFolder(RGBDSource):
    name = "folder"
    IMAGE_EXTS = (".exr", ".png")
    DEPTH_EXTS = (".exr", ".npy", ".png")

    def __init__(self, root):
        self.root = Path(root)
        if not (self.root / "images").is_dir() or not (self.root / "depth").is_dir():
            raise ModelError(f"{self.root}: expected folders images/ and depth/ (see dcdi_core.dataset.rgbd)")
        stems = {p.stem for p in (self.root / "images").iterdir() if p.suffix.lower() in self.IMAGE_EXTS}
        self._ids = sorted(stems)
        sp = self.root / "scenes.json"
        self.scenes = loads(sp.read_text(encoding="utf-8"), sp) if sp.exists() else {}

    def ids(self):
        return list(self._ids)

    def scene(self, id):
        return str(self.scenes.get(id, id))

    def load(self, id):
        img = read_image(_first(self.root / "images", id, self.IMAGE_EXTS, "image"))
        dep = read_any_depth(_first(self.root / "depth", id, self.DEPTH_EXTS, "depth"))
        if dep.shape != img.shape[:2]:
            raise ModelError(f"{self.root}: depth of '{id}' is {dep.shape}, its image {img.shape[:2]}")
        return RGBDFrame(id, self.scene(id), img, dep, self.name)


def _h5py():
    try:
        import h5py
    except ImportError as e:
        raise ModelError(f"reading NYUv2's .mat (HDF5) needs h5py ({e}); pip install h5py==3.16.0") from None
    return h5py


class NYUv2Labeled(RGBDSource):
    name = "nyuv2"

    def __init__(self, path):
        self.path = Path(path)
        h5py = _h5py()
        try:
            with h5py.File(self.path, "r") as f:
                for k in ("images", "depths"):
                    if k not in f:
                        raise ModelError(f"{self.path}: no '{k}' dataset (not NYUv2's labeled .mat?)")
                n = f["images"].shape[0]
                if f["depths"].shape[0] != n or f["images"].ndim != 4 or f["images"].shape[1] != 3:
                    raise ModelError(f"{self.path}: images {f['images'].shape} and depths {f['depths'].shape}: "
                                     "expected (N, 3, W, H) and (N, W, H)")
                self._scenes = self._read_scenes(f, n)
        except OSError as e:
            raise ModelError(f"{self.path}: not readable as HDF5 / MATLAB v7.3 ({e})") from None
        self.n = n

    @staticmethod
    def _read_scenes(f, n):
        if "scenes" not in f:
            return [f"nyu{i:04d}" for i in range(n)]
        refs = np.asarray(f["scenes"]).reshape(-1)
        out = []
        for r in refs:
            chars = np.asarray(f[r]).reshape(-1)
            out.append("".join(chr(int(c)) for c in chars))
        return out

    def ids(self):
        return [f"{i:04d}" for i in range(self.n)]

    def scene(self, id):
        return self._scenes[int(id)]

    def load(self, id):
        i = int(id)
        h5py = _h5py()
        with h5py.File(self.path, "r") as f:
            img8 = np.asarray(f["images"][i]).transpose(2, 1, 0)        # (3, W, H) -> (H, W, 3)
            dep = np.asarray(f["depths"][i], dtype=np.float32).T        # (W, H) -> (H, W)
        img = srgb_to_linear(img8.astype(np.float64) / 255.0).astype(np.float32)
        dep = np.where(dep > 0, dep, np.nan).astype(np.float32)
        return RGBDFrame(id, self.scene(id), np.ascontiguousarray(img), np.ascontiguousarray(dep), self.name)


# ------------------------------------------------------------- Middlebury
def read_pfm(path) -> np.ndarray:
    """A PFM file ('Pf' grey or 'PF' colour, scale < 0 little-endian) as
    float32 (H, W) or (H, W, 3), top row first."""
    path = Path(path)
    with open(path, "rb") as f:
        kind = f.readline().strip()
        if kind not in (b"Pf", b"PF"):
            raise ImageFileError(path, f"not a PFM file (header {kind[:8]!r})")
        dims = f.readline().split()
        while not dims:
            dims = f.readline().split()
        w, h = int(dims[0]), int(dims[1])
        scale = float(f.readline().strip())
        ch = 3 if kind == b"PF" else 1
        data = np.frombuffer(f.read(), dtype="<f4" if scale < 0 else ">f4")
    if data.size != w * h * ch:
        raise ImageFileError(path, f"holds {data.size} values, its header says {w} x {h} x {ch}")
    data = data.reshape(h, w, ch)[::-1].astype(np.float32)             # PFM stores the bottom row first
    return np.ascontiguousarray(data[..., 0] if ch == 1 else data)


def read_middlebury_calib(path) -> dict:
    """calib.txt -> {'f', 'cx', 'cy', 'doffs', 'baseline', ...} (pixels, mm)."""
    path = Path(path)
    out = {}
    for line in path.read_text(encoding="utf-8").splitlines():
        if "=" not in line:
            continue
        k, v = (s.strip() for s in line.split("=", 1))
        if k.startswith("cam"):
            nums = [float(x) for x in re.split(r"[\s;\[\]]+", v) if x]
            if len(nums) != 9:
                raise ModelError(f"{path}: {k} must be a 3 x 3 matrix, got {v!r}")
            out[k] = nums
        else:
            try:
                out[k] = float(v)
            except ValueError:
                out[k] = v
    for k in ("cam0", "doffs", "baseline"):
        if k not in out:
            raise ModelError(f"{path}: no '{k}' (Middlebury 2014 calib.txt has cam0, doffs, baseline)")
    out["f"], out["cx"], out["cy"] = out["cam0"][0], out["cam0"][2], out["cam0"][5]
    return out


def middlebury_depth_m(disparity, calib: dict) -> np.ndarray:
    """Z = baseline f / (d + doffs), mm -> m; unknown (inf, NaN, <= -doffs) -> NaN."""
    d = np.asarray(disparity, dtype=np.float64)
    den = d + calib["doffs"]
    ok = np.isfinite(d) & (den > 0)
    z = np.full(d.shape, np.nan)
    z[ok] = calib["baseline"] * calib["f"] / den[ok] / 1000.0
    return z.astype(np.float32)


class Middlebury2014(RGBDSource):
    name = "middlebury2014"

    def __init__(self, root):
        self.root = Path(root)
        self._ids = sorted(p.name for p in self.root.iterdir() if (p / "calib.txt").exists()) \
            if self.root.is_dir() else []
        if not self._ids:
            raise ModelError(f"{self.root}: no scene folders with calib.txt, im0.png and disp0.pfm")

    def ids(self):
        return list(self._ids)

    def scene(self, id):
        return id.split("-")[0]

    def load(self, id):
        d = self.root / id
        calib = read_middlebury_calib(d / "calib.txt")
        img = read_image(d / "im0.png")
        dep = middlebury_depth_m(read_pfm(d / "disp0.pfm"), calib)
        if dep.shape != img.shape[:2]:
            raise ModelError(f"{d}: disparity {dep.shape} and image {img.shape[:2]} differ")
        return RGBDFrame(id, self.scene(id), img, dep, self.name, {"calib": calib})


READERS = {"factory": FactoryFolder, "folder": RGBDFolder, "nyuv2": NYUv2Labeled, "middlebury2014": Middlebury2014}


def open_source(path, kind: str | None = None) -> RGBDSource:
    """The reader for ``path``: ``kind`` one of READERS, or found from what is there."""
    path = Path(path)
    if kind is not None:
        if kind not in READERS:
            raise ModelError(f"RGB-D source kind {kind!r}; allowed: {', '.join(READERS)}")
        return READERS[kind](path)
    if path.is_file() and path.suffix.lower() == ".mat":
        return NYUv2Labeled(path)
    if ff.is_factory_folder(path):
        return FactoryFolder(path)
    if (path / "images").is_dir():
        return RGBDFolder(path)
    if path.is_dir() and any((p / "calib.txt").exists() for p in path.iterdir()):
        return Middlebury2014(path)
    raise ModelError(f"{path}: not an RGB-D source this project reads (a factory folder with manifest.jsonl, "
                     "a folder with images/ and depth/, NYUv2's labeled .mat, or Middlebury 2014 scene folders)")

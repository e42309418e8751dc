"""A user's folder of image textures: photographs, or material sets.

The factory maps these onto scene surfaces (``--textures DIR``), in Blender
and in the numpy recipe alike. Two kinds of file are understood:

* a **material set** in the convention CC0 libraries use (ambientCG:
  ``Bricks059_1K-JPG_Color.jpg`` beside ``..._NormalGL.jpg`` and
  ``..._Roughness.jpg``; Poly Haven: ``brick_wall_diff_1k.jpg`` beside
  ``brick_wall_nor_gl_1k.exr`` and ``brick_wall_rough_1k.jpg``): files in one
  folder whose names differ only by the map's word form one set, its colour
  map required, normal and roughness maps used when present, other maps
  (displacement, ambient occlusion, metalness, opacity) ignored;
* any other image is a **colour-only set** of its own (a photograph).

Images are PNG, JPEG or EXR (8- and 16-bit files are sRGB colour, EXR
linear; see :mod:`dcdi_core.io.images`). The folder is searched
recursively, in sorted order, so the same folder gives the same sets on
every machine. Every file is opened (its header read) when the library is
made, so an unreadable file is refused before any render.
"""
from __future__ import annotations

import hashlib
import re
from dataclasses import dataclass
from pathlib import Path

from ..errors import DatasetError, InputRangeError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".exr")

# the map's word in a file name (lower case, between separators) -> its role
_MAP_WORDS = {
    "colour": ("color", "colour", "albedo", "diffuse", "diff", "basecolor", "basecolour", "col"),
    "normal_gl": ("normalgl", "normal", "nor_gl", "nrm", "nor", "norm"),
    "normal_dx": ("normaldx", "nor_dx"),
    "roughness": ("roughness", "rough", "rgh"),
    "other": ("displacement", "disp", "height", "ambientocclusion", "ao", "arm", "metalness", "metallic",
              "metal", "opacity", "alpha", "specular", "spec", "emission", "bump", "mask", "idmask"),
}
_WORD_ROLE = {w: role for role, words in _MAP_WORDS.items() for w in words}
# the longest words first, so that "nor_gl" wins over "nor"
_MAP_RE = re.compile(r"(?:^|[_\-. ])(" + "|".join(sorted(map(re.escape, _WORD_ROLE), key=len, reverse=True))
                     + r")(?=$|[_\-. ])", re.IGNORECASE)


@dataclass(frozen=True)
class TextureSet:
    """One surface's maps: ``colour`` (required), ``normal`` (tangent-space,
    OpenGL convention unless ``normal_convention == 'dx'``: green flipped),
    ``roughness`` (grey). ``name`` is the path relative to the library's
    folder, without the map word."""
    name: str
    colour: Path
    normal: Path | None = None
    normal_convention: str = "gl"
    roughness: Path | None = None

    @property
    def files(self) -> tuple[Path, ...]:
        return tuple(p for p in (self.colour, self.normal, self.roughness) if p is not None)


def _classify(path: Path) -> tuple[str, str]:
    """(set key, role) of an image file: the key is its stem with the map's
    word cut out; a file without a map word is a colour-only set."""
    stem = path.name[: -len(path.suffix)]
    matches = list(_MAP_RE.finditer(stem))
    if not matches:
        return stem, "colour"
    m = matches[-1]             # the map word is the last one (a set may be named "wood_diff..")
    role = _WORD_ROLE[m.group(1).lower()]
    key = (stem[: m.start()] + "|" + stem[m.end():]).strip("_-. ")
    return key, role


def _check_readable(path: Path, pixels: bool = False) -> None:
    """Read the file's header, raising DatasetError naming it; ``pixels``:
    refuse also a file whose pixels dcdi_core.io.images could not decode
    here (without OpenImageIO only EXR is read)."""
    from ..io.image_checks import image_size
    from ..io.image_file import ImageFileError
    try:
        h, w = image_size(path, pixels=pixels)
    except ImageFileError as e:
        raise DatasetError(f"--textures: {e}") from None
    if w < 1 or h < 1:
        raise DatasetError(f"--textures: {path}: an image of {w} x {h} pixels (allowed: at least 1 x 1)")


def _group(files: list[Path], root: Path) -> list[TextureSet]:
    groups: dict[tuple[Path, str], dict[str, Path]] = {}
    for f in files:
        key, role = _classify(f)
        if role == "other":
            continue
        groups.setdefault((f.parent, key), {}).setdefault(role, f)
    sets = []
    for (parent, key), maps in sorted(groups.items(), key=lambda kv: (str(kv[0][0]), kv[0][1])):
        if "colour" not in maps:
            continue            # a normal map without its colour: nothing to show
        normal = maps.get("normal_gl") or maps.get("normal_dx")
        name = str((parent / key.replace("|", "")).relative_to(root))
        sets.append(TextureSet(name=name, colour=maps["colour"], normal=normal,
                               normal_convention="gl" if normal is None or "normal_gl" in maps else "dx",
                               roughness=maps.get("roughness")))
    return sets


@dataclass(frozen=True)
class TextureLibrary:
    """The texture sets found in ``folder`` (see the module's docstring)."""
    folder: Path
    sets: tuple[TextureSet, ...]

    @classmethod
    def from_folder(cls, folder, option: str = "--textures", *, pixels: bool = False) -> "TextureLibrary":
        """Find and check every set; raises InputRangeError for a missing
        folder or one without a usable image, DatasetError naming an
        unreadable file. Reads headers only (fast). ``pixels``: the pixels
        will be decoded by dcdi_core.io.images (the numpy recipe), not by
        Blender: refuse files it cannot decode here too."""
        root = Path(folder).expanduser()
        if not root.is_dir():
            raise InputRangeError(option, str(folder), "a folder of PNG, JPEG or EXR images"
                                  + (" (this is a file)" if root.exists() else " (not found)"))
        files = sorted(p for p in root.rglob("*") if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES
                       and not any(part.startswith(".") for part in p.relative_to(root).parts))
        sets = _group(files, root)
        if not sets:
            found = f"{len(files)} image files, none a colour map" if files else "no image files"
            raise InputRangeError(option, str(folder), f"a folder holding at least one PNG, JPEG or EXR colour "
                                  f"image ({found})")
        for s in sets:
            for f in s.files:
                _check_readable(f, pixels)
        return cls(folder=root, sets=tuple(sets))

    def pick(self, rng) -> TextureSet:
        """One set drawn with ``rng`` (numpy Generator)."""
        return self.sets[int(rng.integers(len(self.sets)))]

    def fingerprint(self) -> str:
        """Hash of every set's files' relative names and sizes: a resume with
        another folder's content is refused (dataset.json records it)."""
        h = hashlib.sha256()
        for s in self.sets:
            for f in s.files:
                h.update(f"{f.relative_to(self.folder)}\0{f.stat().st_size}\0".encode())
        return h.hexdigest()[:16]

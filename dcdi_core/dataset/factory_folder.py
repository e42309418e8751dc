"""The dataset factory's folder format, defined once.

Written by the factory (blender_addon/factory/: ``batch`` makes a folder,
``merge_shards`` makes one of several), read by ``dataset.rgbd.FactoryFolder``
(DA2T training) and the developer tools. numpy and the standard library
only (the images through ``dcdi_core.io.images``): no bpy, no torch.

A folder::

    dataset.json                  the run's settings (SETTINGS_FORMAT), compared on every resume
    manifest.jsonl                one JSON record per finished sample, "id" its first key
    merge.json                    a merged folder only: the shards it was made of
    aif/<id>.exr                  all-in-focus render, linear RGB float32
    depth/<id>.exr                planar depth in metres from the lens's first vertex ("Z"; background = inf)
    <lens>/aberrated/<id>.exr     depth-aware simulation (with the lens's distortion)
    <lens>/baseline/<id>.exr      depth-unaware baseline (one depth for the whole image)
    <lens>/sharp/<id>.exr         the all-in-focus image distorted like the others (the aligned target)
    .<id>.render.exr              the renderer's hand-over file while the sample renders (then removed)

Paired folders share file names, so paired-folder loaders read them
directly. ``<id>`` is ``<recipe>-<index>``, the index written with at least
6 digits (:func:`sample_id`, :func:`parse_sample_id`). A sample counts only
once its manifest record is complete: a record torn by a kill (the last
line, or one with the next record glued to it) does not count
(:func:`read_manifest`). Every file is written under a temporary name and
renamed (``dcdi_core.atomic``); the manifest grows by one flushed line per
sample (:func:`append_record`).
"""
from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass
from pathlib import Path

from ..io.jsontext import loads
from ..names import check_name

SETTINGS_FILE = "dataset.json"
MANIFEST = "manifest.jsonl"
MERGE_RECORD = "merge.json"
SETTINGS_FORMAT = 1                # dataset.json's "format": raised when its fields change meaning
AIF_DIR = "aif"
DEPTH_DIR = "depth"
LENS_KINDS = ("aberrated", "baseline", "sharp")
IMAGE_EXT = ".exr"
INDEX_DIGITS = 6
RENDER_HANDOVER_SUFFIX = ".render.exr"

_RECIPE = r"[a-z][a-z0-9_]*"
_SAMPLE_ID = re.compile(rf"^({_RECIPE})-(\d{{{INDEX_DIGITS},}})$")
_HANDOVER = re.compile(rf"^\.{_RECIPE}-\d{{{INDEX_DIGITS},}}{re.escape(RENDER_HANDOVER_SUFFIX)}$")
# where a record glued behind a torn one starts (records are written with "id" first: record_line)
_RECORD_START = '{"id": '


# ------------------------------------------------------------------ sample ids
def sample_id(recipe: str, index: int) -> str:
    """The id of sample ``index`` (>= 0) of ``recipe``: 'room-000042'."""
    if not re.fullmatch(_RECIPE, recipe or ""):
        raise ValueError(f"recipe name {recipe!r}: lower-case letters, digits and '_', a letter first")
    if not (isinstance(index, int) and index >= 0):
        raise ValueError(f"sample index {index!r}: an integer >= 0")
    return f"{recipe}-{index:0{INDEX_DIGITS}d}"


def parse_sample_id(sid: str) -> tuple[str, int]:
    """(recipe, index) of a sample id; ValueError for anything
    :func:`sample_id` does not write (e.g. 'room-42', 'room-0000042')."""
    m = _SAMPLE_ID.match(sid) if isinstance(sid, str) else None
    if m is None or sample_id(m.group(1), int(m.group(2))) != sid:
        raise ValueError(f"sample id {sid!r}: expected <recipe>-<index, {INDEX_DIGITS} digits>, e.g. 'room-000042'")
    return m.group(1), int(m.group(2))


def is_render_handover(name: str) -> bool:
    """Whether a file name is a sample's render hand-over file (.<id>.render.exr)."""
    return bool(_HANDOVER.match(name))


# ------------------------------------------------------------------ paths
def sample_files(sid: str, lenses) -> list[Path]:
    """Every file of a finished sample, relative to the folder: its AiF
    image, its depth, then per lens its aberrated, baseline and sharp image."""
    _names(sid, lenses)
    rels = [Path(AIF_DIR) / f"{sid}{IMAGE_EXT}", Path(DEPTH_DIR) / f"{sid}{IMAGE_EXT}"]
    return rels + [Path(lens) / kind / f"{sid}{IMAGE_EXT}" for lens in lenses for kind in LENS_KINDS]


def _names(sid: str, lenses=(), root=None) -> None:
    """Refuse a sample id or lens id that is not a name (``names.NAME_RULE``)
    before it becomes part of a path below ``root``: read from a manifest or a
    settings record, '../x' would reach outside the folder."""
    check_name(sid, "sample id", root)
    for i, lens in enumerate(lenses):
        check_name(lens, f"lenses[{i}]", root)


@dataclass(frozen=True)
class FolderLayout:
    """The paths of one factory folder."""

    root: Path

    def __post_init__(self):
        object.__setattr__(self, "root", Path(self.root))

    @property
    def manifest(self) -> Path:
        return self.root / MANIFEST

    @property
    def settings(self) -> Path:
        return self.root / SETTINGS_FILE

    @property
    def merge_record(self) -> Path:
        return self.root / MERGE_RECORD

    # every path of a sample checks its ids are names (DatasetError naming the folder): the last guard
    # of the folder's bounds, whoever read the ids
    def aif(self, sid: str) -> Path:
        _names(sid, root=self.root)
        return self.root / AIF_DIR / f"{sid}{IMAGE_EXT}"

    def depth(self, sid: str) -> Path:
        _names(sid, root=self.root)
        return self.root / DEPTH_DIR / f"{sid}{IMAGE_EXT}"

    def lens_image(self, lens: str, kind: str, sid: str) -> Path:
        """<lens>/<kind>/<id>.exr; ``kind`` one of LENS_KINDS."""
        if kind not in LENS_KINDS:
            raise ValueError(f"image kind {kind!r}: one of {', '.join(LENS_KINDS)}")
        _names(sid, root=self.root)
        check_name(lens, "lens", self.root)
        return self.root / lens / kind / f"{sid}{IMAGE_EXT}"

    def files(self, sid: str, lenses) -> list[Path]:
        return [self.root / rel for rel in sample_files(sid, lenses)]

    def render_handover(self, sid: str) -> Path:
        """Where the renderer hands a sample's image and depth over (a hidden file, removed once read)."""
        _names(sid, root=self.root)
        return self.root / f".{sid}{RENDER_HANDOVER_SUFFIX}"


def is_factory_folder(path) -> bool:
    """A folder with a manifest (every factory folder has one, a settings record only since format 1)."""
    return (Path(path) / MANIFEST).is_file()


# ------------------------------------------------------------------ the manifest
def record_line(record: dict) -> str:
    """One manifest line: the record as JSON, "id" its first key (so that
    :func:`read_manifest` finds a record glued behind a torn one)."""
    return json.dumps({"id": record["id"], **record}) + "\n"


def read_manifest(manifest, *, repair: bool = False) -> tuple[list[dict], list[str]]:
    """(records, notes): the complete records of ``manifest`` (none if there
    is no file). A record torn by a kill while it was appended (invalid JSON,
    or no newline at the end) does not count; with ``repair`` the file is
    rewritten without it (and a complete record glued to a torn one is
    kept), atomically, and ``notes`` says what was dropped. A complete
    record whose "id" is not a name (``names.NAME_RULE``: ids become file
    names) is refused: a DatasetError naming the file and the line."""
    manifest = Path(manifest)
    if not manifest.exists():
        return [], []
    lines = manifest.read_bytes().decode("utf-8", errors="replace").split("\n")
    records, notes, clean = [], [], True
    for n, line in enumerate(lines):
        if not line.strip():
            continue
        rec = _record(line)
        if n == len(lines) - 1:               # no newline after it: written, or torn, by a killed run
            clean = False
            if rec is None:
                notes.append(f"dropped a torn last record ({len(line)} bytes): its sample is done again")
                continue
        elif rec is None:                     # a torn record, perhaps with the next one glued to it
            clean = False
            at = line.rfind(_RECORD_START)
            rec = _record(line[at:]) if at > 0 else None
            if rec is None:
                notes.append(f"dropped a torn record at line {n + 1}: its sample is done again")
                continue
            notes.append(f"dropped a torn record at line {n + 1}, kept {rec['id']} glued to it")
        check_name(rec["id"], "id", f"{manifest}, line {n + 1}")
        records.append(rec)
    if repair and not clean:
        write_manifest(manifest, records)
    return records, notes


def _record(line: str):
    try:
        rec = loads(line, "a manifest line")
    except ValueError:                  # a torn or damaged line (JsonTextError is one)
        return None
    return rec if isinstance(rec, dict) and isinstance(rec.get("id"), str) else None


def finished_ids(manifest) -> set[str]:
    """Ids whose manifest record is complete (a torn record does not count)."""
    return {r["id"] for r in read_manifest(manifest)[0]}


def finished_samples(root) -> dict[str, dict]:
    """{id: record} of a folder's finished samples (a later record of an id
    replaces an earlier one); the file is only read, never repaired."""
    return {r["id"]: r for r in read_manifest(Path(root) / MANIFEST)[0]}


def append_record(manifest, record: dict) -> None:
    """Append one manifest line in a single write, flushed to disk (a kill
    can tear only this line: :func:`read_manifest` drops or repairs it)."""
    from ..errors import output_error
    manifest = Path(manifest)
    try:
        with open(manifest, "a", encoding="utf-8") as f:
            f.write(record_line(record))
            f.flush()
            os.fsync(f.fileno())
    except OSError as e:
        raise output_error(manifest, e) from None


def write_manifest(manifest, records) -> None:
    """The whole manifest, atomically (a merge, a repair, lenses added)."""
    from ..atomic import write_text
    write_text(manifest, "".join(record_line(r) for r in records))


# ------------------------------------------------------------------ the settings record
def settings_record(*, recipe: str, seed: int, shard: str, resolution, lenses, lens_fingerprints: dict,
                    baseline_depth_m: float, render: dict, psf_settings: dict, scene: dict | None = None) -> dict:
    """dataset.json's content: what defines a folder's samples (the count
    may grow, all else must stay). ``resolution`` (rows, cols) pixels;
    ``lenses`` the lens ids in order (the first one's camera renders);
    ``lens_fingerprints`` {id: hash of its optics}; ``baseline_depth_m``
    metres; ``render`` and ``psf_settings`` the renderer's and the PSFs'
    settings as dicts; ``scene`` what else shapes the frames (the recipes'
    version, the texture folder's fingerprint, the exposure)."""
    record = {"format": SETTINGS_FORMAT, "recipe": recipe, "seed": seed, "shard": shard,
              "resolution": list(resolution), "lenses": list(lenses), "lens_fingerprints": dict(lens_fingerprints),
              "baseline_depth_m": baseline_depth_m, "render": dict(render), "psf_settings": dict(psf_settings)}
    if scene is not None:
        record["scene"] = dict(scene)
    return record


def read_settings(root, *, advice: str = "") -> dict | None:
    """A folder's settings record, None when it has none; an unreadable one
    is refused (DatasetError naming the file, then ``advice``)."""
    from ..errors import DatasetError
    path = Path(root) / SETTINGS_FILE
    if not path.exists():
        return None
    try:
        settings = loads(path.read_text(encoding="utf-8"), path)
    except ValueError as e:
        raise DatasetError(f"{path}: unreadable settings record ({e})" + (f"; {advice}" if advice else "")) \
            from None
    if not isinstance(settings, dict):
        raise DatasetError(f"{path}: the settings record is not a JSON object" + (f"; {advice}" if advice else ""))
    lenses = settings.get("lenses")
    if lenses is not None and not isinstance(lenses, list):
        raise DatasetError(f"{path}, field 'lenses': {str(lenses)[:80]!r} is not a list of lens ids")
    for i, lens in enumerate(lenses or []):
        check_name(lens, f"lenses[{i}]", path)                # each names a folder beside aif/
    return settings


def write_settings(root, settings: dict) -> None:
    """dataset.json, atomically."""
    from ..atomic import write_text
    write_text(Path(root) / SETTINGS_FILE, json.dumps(settings, indent=2) + "\n")


def flat_settings(settings: dict, prefix: str = "") -> dict:
    """The settings with nested records flattened to dotted keys
    ('render.samples'), as they are compared; the lens fingerprints stay one
    {id: fingerprint} value."""
    out = {}
    for k, v in settings.items():
        if isinstance(v, dict) and k != "lens_fingerprints":
            out.update(flat_settings(v, f"{prefix}{k}."))
        else:
            out[prefix + k] = v
    return out


def settings_from_manifest(record: dict) -> dict:
    """The settings a folder made before dataset.json existed was made with,
    as far as its first manifest record tells them."""
    render = {k: v for k, v in record.get("render", {}).items() if k not in ("engine", "device", "seconds")}
    out = {"recipe": record.get("recipe"), "seed": record.get("dataset_seed"),
           "resolution": record.get("resolution"), "lenses": list(record.get("lenses", {})),
           "render": render, "psf_settings": record.get("psf_settings", {})}
    base = [v.get("baseline_depth_m") for v in record.get("lenses", {}).values() if isinstance(v, dict)]
    if base and base[0] is not None:
        out["baseline_depth_m"] = base[0]
    return {k: v for k, v in out.items() if v is not None}


# ------------------------------------------------------------------ a sample's images
def write_rgbd(layout: FolderLayout, sid: str, image, depth) -> None:
    """aif/<id>.exr (linear RGB (H, W, 3)) and depth/<id>.exr ((H, W) metres, inf = background)."""
    from ..io.images import write_depth, write_image
    write_image(layout.aif(sid), image)
    write_depth(layout.depth(sid), depth)


def write_lens_images(layout: FolderLayout, lens: str, sid: str, *, aberrated, baseline, sharp,
                      record=None) -> None:
    """<lens>/aberrated|baseline|sharp/<id>.exr, each linear RGB (H, W, 3).
    ``record``: the aberrated image's capture record
    (``io.capture_record.CaptureRecord``), kept in its header (the baseline's
    too, marked depth-unaware)."""
    from dataclasses import replace

    from ..io.images import write_image
    records = (record, None if record is None else replace(record, extra={**record.extra, "depth_aware": False}),
               None)
    for kind, img, rec in zip(LENS_KINDS, (aberrated, baseline, sharp), records):
        write_image(layout.lens_image(lens, kind, sid), img, record=rec)


def read_rgbd(layout: FolderLayout, sid: str):
    """(image (H, W, 3) float32 linear, depth (H, W) float32 metres) of a sample."""
    from ..io.images import read_depth, read_image
    return read_image(layout.aif(sid)), read_depth(layout.depth(sid))


def read_lens_images(layout: FolderLayout, lens: str, sid: str) -> dict:
    """{kind: (H, W, 3) float32} of a lens's simulation of a sample, kind in LENS_KINDS."""
    from ..io.images import read_image
    return {kind: read_image(layout.lens_image(lens, kind, sid)) for kind in LENS_KINDS}

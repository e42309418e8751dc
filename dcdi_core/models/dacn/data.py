"""DA2T training pairs: all-in-focus RGB-D frames through the lens simulator.

The degradation of one frame (:func:`degrade`), in this order:

1. the lens perturbed within +-``perturb_fraction`` (radii and
   thicknesses, ``optics.perturb``), from a seed drawn for this frame and
   variant; a draw whose surfaces no longer fit is replaced by the next
   seed; both recorded;
2. the *whole frame* through ``render.simulate.LensSimulator`` of that lens
   (a crop's position in the field decides its PSFs, so crops are taken
   afterwards, from capture, target and depth together): the depth-aware
   capture, the aligned sharp target (distorted alike), the depth on the
   sensor (NaN where nothing is imaged) and the depth-unaware baseline
   (every patch blurred with the PSFs of ``baseline_depth_m``) from the
   same frame and lens;
3. sensor noise (``render.noise``) on the capture and the baseline, each
   with its own recorded seed;
4. saturation (``saturate``): capture, baseline and target clipped to
   [0, 1], what a sensor of full well 1 records. Rendered frames are linear
   HDR (the factory's lamps and windows exceed 1): blurred before clipping,
   a highlight blooms in the capture as in a real camera, and the target is
   what an ideal lens on the same sensor records, so the network is never
   asked for values above 1 that no 8-bit or clipped image holds.

The frame's geometry: it spans the sensor's diagonal (``sensor_px`` None),
or it is the centred crop of a ``sensor_px`` = (rows, cols) sensor at that
sensor's pixel pitch (the paper treats NYUv2's 480 x 640 frames as part of
a 1280 x 1920 sensor).

Pairs are pre-built on disk (:func:`build_pairs`: one ``.npy`` per frame and
variant, (H, W, 10) float32 = capture, target, baseline (3 each) and depth,
written atomically, a ``pairs.jsonl`` line each with its record; a killed
build restarted with the same arguments does only what is missing;
``shard`` splits the work) and cropped on the fly by :class:`PairCrops`
from memory-mapped files (a crop reads its own rows only, so a data set far
larger than memory trains at the speed of one that fits).

Cost (measured, 480 x 640, default PSF settings, one core): the PSF library
of a perturbed lens ~25 s, the simulation itself 1.3-2.4 s; so
``lens_pool`` = K draws K perturbed lenses once (seeded, their libraries
cached on disk) and gives each frame one of them, instead of a new lens per
frame (``lens_pool`` 0, the paper's per-sample perturbation).
"""
from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import numpy as np

from ...atomic import atomic_path
from ...errors import DatasetError, InputRangeError
from ...io.jsontext import loads
from ...names import check_name
from ...optics.errors import OpticsError
from ...errors import ModelError, ModelFileError
from ..runtime.depth_encoding import encode_depth

PERTURB_TRIES = 10
PLACEMENTS = ("random", "centre")


def _default_noise():
    return {"full_well_electrons": 10000.0, "read_noise_electrons": 3.0}


@dataclass(frozen=True)
class DA2TConfig:
    """How frames become training pairs. PSF and grid fields are those of
    ``psf.compute.PSFSettings`` and ``psf.library.LibraryGrid``."""

    lens: str = "mos-s2"
    perturb_fraction: float = 0.10
    # the perturbed lens's sensor moved back to the nominal focus (optics.perturb); False in configs
    # written before this setting existed (their pairs were made without it)
    refocus: bool = True
    noise: dict | None = field(default_factory=_default_noise)     # add_sensor_noise kwargs; None: none
    baseline_depth_m: float = 2.0
    patch: int = 16
    sensor_px: tuple | None = None
    # with sensor_px: 'random' places each frame and variant at a seeded spot of the sensor (every field
    # reached), 'centre' at its centre; 'centre' in configs written before this setting existed
    placement: str = "random"
    # the capture's deconvolution with the *nominal* lens's PSFs (correct.deconvolution, its defaults, the
    # noise estimated from the capture: what `dcdi correct` feeds a refining network), stored with the pair
    deconvolved: bool = True
    pupil_samples: int = 64
    n_wavelengths: int = 31
    n_fields: int = 64
    n_depths: int = 20
    lens_pool: int = 0               # 0: a new perturbed lens per frame and variant; K: one of K lenses
    saturate: bool = True            # every image of a pair in [0, 1], as a sensor records it
    seed: int = 0

    def __post_init__(self):
        if self.sensor_px is not None:
            object.__setattr__(self, "sensor_px", tuple(int(v) for v in self.sensor_px))
        if not (0.0 <= self.perturb_fraction <= 0.5):
            raise InputRangeError("perturb_fraction", self.perturb_fraction, "[0, 0.5] (0.1 = +-10 %)")
        if self.lens_pool < 0:
            raise InputRangeError("lens_pool", self.lens_pool, ">= 0 (0: a new lens per frame)")
        if self.placement not in PLACEMENTS:
            raise InputRangeError("placement", self.placement, " or ".join(PLACEMENTS))

    def as_dict(self) -> dict:
        d = asdict(self)
        d["sensor_px"] = list(self.sensor_px) if self.sensor_px else None
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "DA2TConfig":
        names = {f.name for f in fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise InputRangeError("DA2T setting", sorted(unknown), ", ".join(sorted(names)))
        return cls(**{"refocus": False, "placement": "centre", "deconvolved": False, **d})


@dataclass
class DA2TPair:
    id: str                      # frame id (with the variant: '<frame>~<k>')
    scene: str
    capture: np.ndarray          # (H, W, 3) float32: depth-aware aberrated, noisy
    target: np.ndarray           # (H, W, 3) float32: the sharp frame on the sensor
    baseline: np.ndarray         # (H, W, 3) float32: depth-unaware aberrated, noisy
    depth: np.ndarray            # (H, W) float32 metres on the sensor (NaN: nothing imaged)
    record: dict = field(default_factory=dict)
    deconvolved: np.ndarray | None = None    # (H, W, 3) float32: the capture deconvolved with the nominal lens

    def geometry(self) -> tuple:
        """(center_px, pixel_pitch_mm, semi_diagonal_mm) of the frame on the sensor (its record's)."""
        g = self.record.get("geometry")
        if not g:
            raise ModelError(f"pair {self.id}: no geometry in its record (pairs built before it was recorded; "
                             "build them again for field conditioning)")
        return tuple(g["center_px"]), g["pixel_pitch_mm"], g["semi_diagonal_mm"]


def _seeds(config: DA2TConfig, frame_id: str, variant: int):
    """(perturbation, capture noise, baseline noise, placement) seeds of one
    frame and variant; with a lens pool the perturbation seed is that of the
    pool's lens the frame draws."""
    key = [config.seed, variant] + list(frame_id.encode())
    s = [int(v) for v in np.random.SeedSequence(key).generate_state(5, dtype=np.uint32)]
    if config.lens_pool:
        member = s[3] % config.lens_pool
        s[0] = int(np.random.SeedSequence([config.seed, 1 << 20, member]).generate_state(1, dtype=np.uint32)[0])
    return s[0], s[1], s[2], s[4]


def perturbed(lens, fraction: float, seed: int, refocus: bool = True):
    """(lens, record): the first seed from ``seed`` on whose draw fits."""
    from ...optics.perturb import perturb_lens

    if fraction == 0:
        return lens, {"seed": None, "fraction": 0.0, "changes": []}
    errors = []
    for k in range(PERTURB_TRIES):
        try:
            plens, rec = perturb_lens(lens, seed=seed + k, fraction=fraction, refocus=refocus)
            rec["rejected_seeds"] = errors
            return plens, rec
        except OpticsError:
            errors.append(seed + k)
    raise ModelError(f"lens {lens.id}: no perturbation within +-{fraction:.0%} fits from seed {seed} "
                     f"({PERTURB_TRIES} draws); lower perturb_fraction")


def frame_top_left(h: int, w: int, sensor_px, placement: str, seed: int) -> tuple[int, int]:
    """(top row, left column) of an h x w frame on a ``sensor_px`` sensor:
    its centre ('centre'), or uniform over the places it fits ('random',
    seeded)."""
    rows, cols = sensor_px
    if h > rows or w > cols:
        raise InputRangeError("frame size", (h, w), f"within the sensor_px {tuple(sensor_px)}")
    if placement == "centre":
        return (rows - h) // 2, (cols - w) // 2
    rng = np.random.default_rng(seed)
    return int(rng.integers(0, rows - h + 1)), int(rng.integers(0, cols - w + 1))


def frame_geometry(lens, h: int, w: int, sensor_px=None, top_left=None):
    """The frame's ``ImageGeometry``: spanning the sensor's diagonal
    (``sensor_px`` None), or an h x w crop of a ``sensor_px`` sensor at that
    sensor's pitch whose top-left pixel is sensor pixel ``top_left``
    (default: centred)."""
    from ...render.geometry import ImageGeometry

    if sensor_px is None:
        return ImageGeometry.full_sensor(lens, h, w)
    rows, cols = sensor_px
    r0, c0 = frame_top_left(h, w, sensor_px, "centre", 0) if top_left is None else top_left
    if h > rows or w > cols or not (0 <= r0 <= rows - h and 0 <= c0 <= cols - w):
        raise InputRangeError("frame size and place", (h, w, r0, c0), f"within the sensor_px {tuple(sensor_px)}")
    pitch = ImageGeometry.full_sensor(lens, rows, cols).pixel_pitch_mm
    return ImageGeometry.from_pixel_pitch(lens, h, w, pitch, center_px=((rows - 1) / 2 - r0, (cols - 1) / 2 - c0))


def _library(lens, key, geom, config: DA2TConfig, libraries: dict | None, reuse: bool):
    """The PSF library of ``lens`` at ``geom``'s pitch, kept in ``libraries``
    under ``key`` when ``reuse``: it holds the whole depth range (grown past
    41 px if a fast lens needs it), not fitted to one frame's depths, so
    every frame of a lens is blurred alike, wherever it lies on the sensor."""
    from ...psf.compute import PSFSettings
    from ...psf.library import LibraryGrid
    from ...psf.sources import open_library

    lib = libraries.get(key) if libraries is not None and reuse else None
    if lib is None:
        grid = LibraryGrid(n_fields=config.n_fields, n_depths=config.n_depths)
        lib = open_library(lens, geom, PSFSettings(pupil_samples=config.pupil_samples,
                                                   n_wavelengths=config.n_wavelengths),
                           grid, cache=reuse, fit_depth_m=np.array([[grid.near_m, grid.far_m, np.inf]]))
        if libraries is not None and reuse:
            libraries[key] = lib
    return lib


def nominal_library(lens, geom, config: DA2TConfig, libraries: dict | None):
    """The nominal ``lens``'s PSF library at ``geom``'s pitch, the one every
    deconvolution of ``config``'s pairs reads (kept in ``libraries``)."""
    return _library(lens, ("nominal", geom.pixel_pitch_mm), geom, config, libraries, True)


def degrade(frame, config: DA2TConfig, variant: int = 0, *, lens=None, simulators: dict | None = None) -> DA2TPair:
    """One frame (``rgbd.RGBDFrame``) through the DA2T degradation (module
    docstring). ``simulators``: a dict kept by the caller in which PSF
    libraries are reused across frames (a lens pool's, the nominal lens's)."""
    from ...optics.lens import load_lens
    from ...render.noise import add_sensor_noise
    from ...render.simulate import LensSimulator, SimulateOptions

    base = lens if lens is not None else load_lens(config.lens)
    s_perturb, s_noise, s_base, s_place = _seeds(config, frame.id, variant)
    plens, prec = perturbed(base, config.perturb_fraction, s_perturb, config.refocus)
    h, w = frame.depth.shape
    top_left = None if config.sensor_px is None else frame_top_left(h, w, config.sensor_px, config.placement,
                                                                     s_place)
    geom = frame_geometry(plens, h, w, config.sensor_px, top_left)
    reuse = config.perturb_fraction == 0 or config.lens_pool > 0    # else: a lens never met again
    lib = _library(plens, (prec["seed"], geom.pixel_pitch_mm), geom, config, simulators, reuse)
    sim = LensSimulator(plens, SimulateOptions(geometry=geom, patch=config.patch,
                                               baseline_depth_m=config.baseline_depth_m), library=lib)
    noise = config.noise
    r = sim(frame.image, frame.depth, noise=noise, seed=s_noise if noise is not None else None)
    baseline = r.baseline if noise is None else add_sensor_noise(r.baseline, seed=s_base, **noise)
    capture, target = r.image, r.sharp
    if config.saturate:
        capture, target, baseline = (np.clip(a, 0.0, 1.0) for a in (capture, target, baseline))
    deconvolved = None
    if config.deconvolved:
        from ...correct.deconvolution import deconvolve
        ngeom = frame_geometry(base, h, w, config.sensor_px, top_left)
        nlib = nominal_library(base, ngeom, config, simulators)
        deconvolved = deconvolve(capture, r.depth, base, geometry=ngeom, library=nlib).image.astype(np.float32)
    record = {"id": f"{frame.id}~{variant}", "frame": frame.id, "scene": frame.scene, "variant": variant,
              "source": frame.source, "lens": base.id, "perturbation": prec,
              "noise": None if noise is None else dict(noise, seed=s_noise, baseline_seed=s_base),
              "baseline_depth_m": config.baseline_depth_m, "sensor_px": config.as_dict()["sensor_px"],
              "top_left": None if top_left is None else list(top_left),
              "geometry": {"center_px": list(geom.center_px), "pixel_pitch_mm": geom.pixel_pitch_mm,
                           "semi_diagonal_mm": geom.semi_diagonal_mm},
              "pixel_pitch_mm": geom.pixel_pitch_mm, "kernel_size": lib.kernel_size,
              "deconvolved": deconvolved is not None,
              "not_imaged_pixels": int(np.isnan(r.depth).sum()), "shape": [h, w]}
    return DA2TPair(record["id"], frame.scene, capture.astype(np.float32), target.astype(np.float32),
                    baseline.astype(np.float32), r.depth.astype(np.float32), record, deconvolved)


# --------------------------------------------------------------- on disk
CHANNELS = {"capture": slice(0, 3), "target": slice(3, 6), "baseline": slice(6, 9), "depth": 9}
DECONVOLVED = slice(10, 13)


def pair_path(root, pair_id: str) -> Path:
    """pairs/<id>.npy below ``root``; ``pair_id`` (read from pairs.jsonl, or a
    frame id and variant) must be a name (``names.NAME_RULE``): '../x' would
    read or write outside the folder (DatasetError naming the folder)."""
    return Path(root) / "pairs" / f"{check_name(pair_id, 'pair id', root)}.npy"


def save_pair(root, pair: DA2TPair) -> Path:
    """pairs/<id>.npy: (H, W, 10) float32, capture | target | baseline |
    depth, then the deconvolved capture if the pair has one (13)."""
    path = pair_path(root, pair.id)
    parts = [pair.capture, pair.target, pair.baseline, pair.depth[..., None]]
    if pair.deconvolved is not None:
        parts.append(pair.deconvolved)
    stack = np.concatenate(parts, axis=2)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.save(f, np.ascontiguousarray(stack, dtype=np.float32), allow_pickle=False)
    return path


def load_pair(path, record: dict | None = None) -> DA2TPair:
    """A pre-built pair, memory-mapped (arrays are views of the file)."""
    path = Path(path)
    try:
        a = np.load(path, mmap_mode="r", allow_pickle=False)
    except (OSError, ValueError) as e:
        raise ModelFileError(path, f"not a DA2T pair ({e})") from None
    if a.ndim != 3 or a.shape[2] not in (10, 13) or a.dtype != np.float32:
        raise ModelFileError(path, f"array {a.shape} {a.dtype}, expected (H, W, 10 or 13) float32")
    rec = record or {}
    dec = a[..., DECONVOLVED] if a.shape[2] == 13 else None
    return DA2TPair(path.stem, rec.get("scene", ""), record=rec, deconvolved=dec,
                    **{k: a[..., c] for k, c in CHANNELS.items()})


def finished_pairs(root) -> dict:
    """{pair id: record} of the pairs whose pairs.jsonl line is complete
    (read as the factory's manifest is: a torn line does not count)."""
    from ...dataset.factory_folder import read_manifest
    path = Path(root) / "pairs.jsonl"
    records = {rec["id"]: rec for rec in read_manifest(path)[0]}
    for pid, rec in records.items():            # what training and evaluation read of each record
        for key in PAIR_KEYS:
            if not isinstance(rec.get(key), str) or not rec[key]:
                what = "missing" if key not in rec else "not a non-empty string"
                raise DatasetError(f"{path}: pair {pid}: field '{key}' is {what}; a pairs.jsonl line as dcdi "
                                   "dacn pairs writes it has it")
        check_name(rec["frame"], f"pair {pid}: frame", path)
    return records


#: the fields of a pairs.jsonl record that training and evaluation rely on
PAIR_KEYS = ("frame", "scene")


def record_settings(root, settings: dict) -> None:
    """``root``/da2t.json: written with ``settings`` in a new folder; in one
    that has it, they must be equal (resumed work never mixes settings)."""
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    path = root / "da2t.json"
    if path.exists():
        old = loads(path.read_text(encoding="utf-8"), path)
        if old != settings:
            diff = sorted(k for k in set(old) | set(settings) if old.get(k) != settings.get(k))
            raise ModelError(f"{root}: pairs built with other DA2T settings ({', '.join(diff)}); use another folder")
    else:
        from ...atomic import write_text
        write_text(path, json.dumps(settings, indent=1, sort_keys=True) + "\n")


def build_pairs(source, root, config: DA2TConfig, *, ids=None, variants: int = 1, shard=(0, 1), log=None) -> dict:
    """Pre-build the pairs of ``source``'s frames (``ids``: a subset) into
    ``root``: pairs/<frame>~<k>.npy and a pairs.jsonl line each, the config
    in da2t.json (a folder built with another config is refused). Resumable;
    ``shard`` (i, n) does the frames whose position mod n is i. Returns
    {pair id: record} of all finished pairs."""
    say = log or (lambda s: None)
    root = Path(root)
    record_settings(root, config.as_dict())
    done = finished_pairs(root)
    i, n = shard
    frame_ids = list(source.ids() if ids is None else ids)
    todo = [(f, k) for pos, f in enumerate(frame_ids) if pos % n == i for k in range(variants)
            if f"{f}~{k}" not in done]
    for f, k in todo:                   # every pair's file name, before any work
        pair_path(root, f"{f}~{k}")
    say(f"DA2T: {len(todo)} pairs to build ({len(done)} done) in {root}")
    from ...dataset.factory_folder import append_record
    from ...optics.lens import load_lens
    lens = load_lens(config.lens)
    frame, simulators = None, {}
    for f, k in todo:
        if frame is None or frame.id != f:
            frame = source.load(f)
        pair = degrade(frame, config, k, lens=lens, simulators=simulators)
        save_pair(root, pair)
        append_record(root / "pairs.jsonl", pair.record)
        done[pair.id] = pair.record
        say(f"  {pair.id}")
    return done


# --------------------------------------------------------------- crops
def crop_position(valid: np.ndarray, size: int, rng, tries: int = 20) -> tuple[int, int]:
    """Top-left (row, col) of a size x size crop whose pixels are all imaged
    if one is found in ``tries`` draws, else the draw with the most."""
    h, w = valid.shape
    if size > h or size > w:
        raise InputRangeError("crop size", size, f"<= the frame's {h} x {w}")
    best, best_n = None, -1
    for _ in range(tries):
        r, c = int(rng.integers(0, h - size + 1)), int(rng.integers(0, w - size + 1))
        n_ok = int(valid[r:r + size, c:c + size].sum())
        if n_ok == size * size:
            return r, c
        if n_ok > best_n:
            best, best_n = (r, c), n_ok
    return best


def augment(arrays, k: int):
    """One of the 8 flips / rotations (k in 0..7) of (H, W, ...) arrays, the
    same for all. For a rotationally symmetric lens a flipped or rotated
    crop is a crop at the mirrored or rotated field position."""
    out = []
    for a in arrays:
        a = np.rot90(a, k % 4, axes=(0, 1))
        if k >= 4:
            a = a[:, ::-1]
        out.append(np.ascontiguousarray(a))
    return out


class PairCrops:
    """Training crops from pre-built pairs: ``sample(rng, batch, size)`` ->
    (input, target, encoded depth[, extras]) arrays (B, C, size, size),
    float32: crops within the imaged area, flips and rotations, depth
    encoded per crop (``encoding``). ``input`` 'capture' (DA2T) or
    'baseline' (the depth-unaware training set) picks what the network is
    fed: both come from the same frames. ``extras``: 'deconvolved' (the
    pair's deconvolved capture, turned with the crop) and 'field'
    (``runtime.conditioning``'s maps of the crop's own sensor pixels, turned
    as a rotated field position is; needs the pairs' records).

    choose: of this many imaged candidate places, the crop is taken where
    the capture is furthest from the target (mean absolute difference):
    crops are drawn where there is something to learn, yet every place
    keeps a chance (1: uniform)."""

    def __init__(self, paths, encoding: str, *, augment: bool = True, cache: bool = True, records=None,
                 choose: int = 1):
        # cache: keep each pair's memory map open (the OS pages in what crops read)
        self.paths = [Path(p) for p in paths]
        if not self.paths:
            raise ModelError("no training pairs (build them first: models.dacn.data.build_pairs)")
        if choose < 1:
            raise InputRangeError("crop choice", choose, ">= 1 candidate place (1: uniform)")
        self.encoding, self.augment, self.choose = encoding, augment, int(choose)
        self.records = records or {}
        self._cache = {} if cache else None

    def pair(self, i: int) -> DA2TPair:
        if self._cache is None:
            return load_pair(self.paths[i], self.records.get(self.paths[i].stem))
        if i not in self._cache:
            self._cache[i] = load_pair(self.paths[i], self.records.get(self.paths[i].stem))
        return self._cache[i]

    def _place(self, pair: DA2TPair, size: int, rng) -> tuple[int, int]:
        valid = ~np.isnan(pair.depth)
        places = [crop_position(valid, size, rng) for _ in range(self.choose)]
        if len(places) == 1:
            return places[0]
        err = [float(np.abs(np.asarray(pair.capture[r:r + size, c:c + size])
                            - np.asarray(pair.target[r:r + size, c:c + size])).mean()) for r, c in places]
        return places[int(np.argmax(err))]

    def crop(self, pair: DA2TPair, size: int, rng, *, input: str = "capture", extras=()):
        r, c = self._place(pair, size, rng)
        sl = (slice(r, r + size), slice(c, c + size))
        arrays = [np.array(a[sl]) for a in (getattr(pair, input), pair.target, pair.depth)]
        if "deconvolved" in extras:
            if pair.deconvolved is None:
                raise ModelError(f"pair {pair.id}: no deconvolved capture (pairs built with deconvolved = False)")
            arrays.append(np.array(pair.deconvolved[sl]))
        k = int(rng.integers(0, 8)) if self.augment else 0
        if k:
            arrays = augment(arrays, k)
        x, y, d = arrays[:3]
        out = [x, y, encode_depth(d, self.encoding)]
        if "deconvolved" in extras:
            out.append(arrays[3])
        if "field" in extras:
            from ..runtime.conditioning import augment_field, field_maps
            centre, pitch, sd = pair.geometry()
            maps = field_maps(centre, pitch, sd, np.arange(r, r + size), np.arange(c, c + size))
            out.append(augment_field(maps, k).transpose(1, 2, 0))
        return tuple(out)

    def sample(self, rng, batch: int, size: int, *, input: str = "capture", extras=()):
        """Stacked crops (B, C, size, size): input, target, depth (1 channel),
        then the ``extras`` in their order."""
        cols = None
        for _ in range(batch):
            got = self.crop(self.pair(int(rng.integers(0, len(self.paths)))), size, rng, input=input,
                            extras=extras)
            got = [a[None] if a.ndim == 2 else a.transpose(2, 0, 1) for a in got]
            cols = [[g] for g in got] if cols is None else [col + [g] for col, g in zip(cols, got)]
        return tuple(np.stack(col) for col in cols)

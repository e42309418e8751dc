"""How well a capture's own blur tells depth (`python -m lab
depth-from-blur`): synthetic captures at the paper's pitch (12.2 um) with
sensor noise (full well 10000 e-, read noise 3 e-), each lens's PSFs,
crops of 384 x 512 px at the sensor's centre and its corner; scenes: 'planes' (4 x 4 fronto-parallel dead-leaves planes,
each at a depth drawn uniform in inverse depth over 0.7-10 m), 'leaves'
(dead-leaves RGB-D frames: occluding shapes at metric depths), and two like
photographs, textured with natural-statistics textures of a set no training
uses (``dataset.natural``, seed 1000): 'natural-planes' (the 4 x 4 planes,
each its own texture) and 'natural' (dead leaves of large shapes).

Rows per lens and scene: the estimator (``dfd.estimate_depth``, defaults)
against the best constant (each frame's own median depth: an oracle no
estimator has) and against the oracle that knows the sharp image (per
tile, the depth whose simulation of the true sharp image is nearest the
capture: what the PSFs allow when the texture is known); AbsRel over
pixels with depth in the library's range, and the estimator's tile error
by texture (tiles' band power above the noise, tertiles), by depth and by
field. Prints markdown tables; the figures of docs/depth.md come from here.
"""
from __future__ import annotations

import argparse
import time

import numpy as np

SIZE = (384, 512)
PITCH_MM = 0.0122


def planes(seed: int, h: int, w: int):
    from dcdi_core.dataset.leaves import leaves_rgbd
    img, _, _ = leaves_rgbd(seed, h, w)
    rng = np.random.default_rng(seed)
    depth = np.empty((h, w), np.float32)
    th, tw = h // 4, w // 4
    for i in range(4):
        for j in range(4):
            depth[i * th:(i + 1) * th, j * tw:(j + 1) * tw] = 1.0 / rng.uniform(1 / 10.0, 1 / 0.7)
    return img, depth


def leaves(seed: int, h: int, w: int):
    from dcdi_core.dataset.leaves import leaves_rgbd
    img, depth, _ = leaves_rgbd(seed, h, w)
    return img, depth


# photograph-like frames: shapes larger than a tile, each textured with a natural-statistics texture
# (dataset.natural) of a set drawn from TEXTURE_SEED, which no training set uses
TEXTURE_SEED = 1000
NATURAL_LEAVES = dict(coverage=1.5, size_exponent=2.2, min_radius_px=16.0, max_radius_frac=0.8, thin_share=0.03,
                      photo_share=1.0, texel_per_px=(0.8, 2.0))
_natural = {}


def natural_library():
    """48 natural-statistics textures of TEXTURE_SEED, written once per process to a temporary folder."""
    if "lib" not in _natural:
        import tempfile

        from dcdi_core.dataset.natural import write_textures
        from dcdi_core.dataset.textures import TextureLibrary
        _natural["dir"] = tempfile.TemporaryDirectory(prefix="dcdi-natural-")
        write_textures(_natural["dir"].name, 48, seed=TEXTURE_SEED)
        _natural["lib"] = TextureLibrary.from_folder(_natural["dir"].name)
    return _natural["lib"]


def natural(seed: int, h: int, w: int):
    from dcdi_core.dataset.leaves import LeavesOptions, leaves_rgbd
    img, depth, _ = leaves_rgbd(seed, h, w, LeavesOptions(**NATURAL_LEAVES), textures=natural_library())
    return img, depth


def natural_planes(seed: int, h: int, w: int):
    """4 x 4 planes (as ``planes``), each its own natural-statistics texture."""
    from dcdi_core.dataset.natural import natural_texture
    _, depth = planes(seed, h, w)
    rng = np.random.default_rng([TEXTURE_SEED, seed])
    img = np.empty((h, w, 3), np.float32)
    th, tw = h // 4, w // 4
    for i in range(4):
        for j in range(4):
            img[i * th:(i + 1) * th, j * tw:(j + 1) * tw] = natural_texture(rng, 256)[:th, :tw]
    return img, depth


SCENES = {"planes": planes, "leaves": leaves, "natural": natural, "natural-planes": natural_planes}


def geometry(lens, where: str):
    from dcdi_core.render.geometry import ImageGeometry
    h, w = SIZE
    if where == "centre":
        return ImageGeometry.from_pixel_pitch(lens, h, w, PITCH_MM)
    sh, sw = lens.sensor.resolution_px
    return ImageGeometry.from_pixel_pitch(lens, h, w, PITCH_MM, ((sh - 1) / 2 - (sh - h), (sw - 1) / 2 - (sw - w)))


def oracle_tiles(img, lens, g, library, capture, tile: int, distortion: bool = True) -> np.ndarray:
    """Per tile, the hypothesis depth whose simulation of the true sharp image
    is nearest the capture (SSE); ``distortion`` False for a sharp image
    already on the sensor (a DA2T pair's target)."""
    from dcdi_core.render.simulate import SimulateOptions, simulate
    depths = np.minimum(library.grid.depths_m[::2], library.grid.far_m)
    h, w = capture.shape[:2]
    nph, npw = -(-h // tile), -(-w // tile)
    err = []
    for d in depths:
        sim = simulate(img, np.full((h, w), d, np.float32), lens, SimulateOptions(geometry=g, distortion=distortion),
                       library=library).image
        e = ((sim - capture) ** 2).sum(-1)
        e = np.pad(e, ((0, nph * tile - h), (0, npw * tile - w)))
        err.append(e.reshape(nph, tile, npw, tile).sum((1, 3)))
    return depths[np.argmin(err, 0)]


def frame(lens, library, scene: str, seed: int, where: str, refine=None, options=None, with_oracle: bool = True):
    from dcdi_core.dfd import estimate_depth
    from dcdi_core.render.noise import add_sensor_noise
    from dcdi_core.render.simulate import SimulateOptions, simulate
    g = geometry(lens, where)
    img, depth = SCENES[scene](seed, *SIZE)
    capture = add_sensor_noise(simulate(img, depth, lens, SimulateOptions(geometry=g), library=library).image,
                               seed=seed + 1)
    t, c = time.perf_counter(), time.process_time()
    est = estimate_depth(capture, library, g, options, refine=refine)
    seconds = (time.perf_counter() - t, time.process_time() - c)
    tile = est.tile_diopters.shape
    s = SIZE[0] // tile[0] if SIZE[0] % tile[0] == 0 else 32
    oracle = oracle_tiles(img, lens, g, library, capture, s) if with_oracle else np.full(tile, np.nan)
    near, far = library.grid.near_m, library.grid.far_m
    ok = np.isfinite(depth) & (depth >= near) & (depth <= far)
    truth = depth[ok]
    tile_truth = depth[s // 2::s, s // 2::s]
    centre = np.stack(np.meshgrid(np.arange(tile[0]) * s + s / 2, np.arange(tile[1]) * s + s / 2, indexing="ij"))
    field = np.minimum(g.field(centre[0].ravel(), centre[1].ravel()).reshape(tile), 1.0)
    gy, gx = np.gradient(capture.mean(-1))
    texture = np.pad(gx ** 2 + gy ** 2, ((0, tile[0] * s - SIZE[0]), (0, tile[1] * s - SIZE[1])))
    texture = texture.reshape(tile[0], s, tile[1], s).mean((1, 3))
    # pixels within 4 px of a depth edge (the true depth jumps by more than 10 % between neighbours)
    logd = np.log(np.where(np.isfinite(depth) & (depth > 0), depth, far))
    jump = np.zeros(depth.shape, bool)
    jump[:, 1:] |= np.abs(np.diff(logd, axis=1)) > 0.1
    jump[1:, :] |= np.abs(np.diff(logd, axis=0)) > 0.1
    from numpy.lib.stride_tricks import sliding_window_view
    edge = sliding_window_view(np.pad(jump, 4), (9, 9)).any(axis=(-1, -2))
    err = np.abs(est.depth_m - depth) / depth
    return {"est": err[ok], "edge": err[ok & edge],
            "const": np.abs(np.median(truth) - truth) / truth,
            "oracle": np.abs(oracle - tile_truth) / tile_truth,
            "tiles": np.abs(1.0 / est.tile_diopters - tile_truth) / tile_truth,
            "conf": est.tile_confidence, "tile_truth": tile_truth, "field": field, "texture": texture,
            "seconds": seconds}


def tables(lenses, scenes, seeds, wheres, refine=None, options=None, with_oracle: bool = True) -> None:
    from dcdi_core.app import PSFRequest, open_source
    from dcdi_core.optics.lens import load_lens
    rows, detail, every = [], [], []
    for lens_id in lenses:
        lens = load_lens(lens_id)
        for scene in scenes:
            frames = []
            for where in wheres:
                library = open_source(lens, geometry(lens, where), PSFRequest()).library
                refiner = None
                if refine:
                    from dcdi_core.app.depth import refinement
                    refiner, _ = refinement("auto" if refine == "shipped" else refine, lens_id, PITCH_MM)
                frames += [frame(lens, library, scene, seed, where, refiner, options, with_oracle) for seed in seeds]
            cat = {k: np.concatenate([np.ravel(f[k]) for f in frames]) for k in
                   ("est", "edge", "const", "oracle", "tiles", "conf", "tile_truth", "field", "texture")}
            every.append(cat)
            est, const = cat["est"].mean(), cat["const"].mean()
            wall = np.mean([f["seconds"][0] for f in frames])
            cpu = np.mean([f["seconds"][1] for f in frames])
            sure = cat["conf"] >= 0.5
            edge = f"{cat['edge'].mean():.3f}" if cat["edge"].size else "-"
            rows.append(f"| {lens_id} | {scene} | {len(frames)} | {est:.3f} | {const:.3f} | {est / const:.2f} | "
                        f"{edge} | {cat['oracle'].mean():.3f} | {cat['tiles'][sure].mean():.3f} ({sure.mean():.0%}) | "
                        f"{wall:.1f} ({cpu:.1f}) |")
            tex = np.quantile(cat["texture"], [1 / 3, 2 / 3])
            for name, sel in (("texture low third", cat["texture"] <= tex[0]),
                              ("texture middle third", (cat["texture"] > tex[0]) & (cat["texture"] <= tex[1])),
                              ("texture high third", cat["texture"] > tex[1]),
                              ("depth < 1.2 m", cat["tile_truth"] < 1.2),
                              ("depth 1.2-3 m", (cat["tile_truth"] >= 1.2) & (cat["tile_truth"] < 3)),
                              ("depth >= 3 m", cat["tile_truth"] >= 3),
                              ("field < 0.5", cat["field"] < 0.5), ("field >= 0.5", cat["field"] >= 0.5)):
                if sel.any():
                    detail.append(f"| {lens_id} | {scene} | {name} | {sel.sum()} | {cat['tiles'][sel].mean():.3f} | "
                                  f"{cat['oracle'][sel].mean():.3f} | {cat['conf'][sel].mean():.2f} |")
    conf = np.concatenate([c["conf"] for c in every])
    hit = np.concatenate([c["tiles"] for c in every]) <= 0.15
    calibration = []
    for lo, hi in ((0.0, 0.2), (0.2, 0.4), (0.4, 0.6), (0.6, 0.8), (0.8, 1.0)):
        sel = (conf >= lo) & ((conf < hi) if hi < 1.0 else (conf <= hi))
        if sel.any():
            calibration.append(f"| {lo:.1f}-{hi:.1f} | {sel.sum()} | {hit[sel].mean():.2f} |")
    print(f"Depth from blur: {SIZE[0]} x {SIZE[1]} crops at {PITCH_MM * 1000:g} um (centre and corner of the "
          f"sensor), noise 10000 e- / 3 e-, seeds {', '.join(map(str, seeds))}\n")
    print("| lens | scene | frames | AbsRel | constant (median) | ratio | AbsRel within 4 px of a depth edge | "
          "oracle (sharp known) | confident tiles (share) | wall s (CPU s) per frame |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    print("\n".join(rows))
    print("\nCalibration (all lenses and scenes above): the share of tiles within 15 % of the truth, by "
          "confidence\n")
    print("| confidence | tiles | within 15 % |")
    print("|---|---|---|")
    print("\n".join(calibration))
    print("\nTile errors (AbsRel of the tiles' estimates before filling):\n")
    print("| lens | scene | tiles | count | AbsRel | oracle | mean confidence |")
    print("|---|---|---|---|---|---|---|")
    print("\n".join(detail))


def pairs_table(pairs: dict, count: int, options=None, oracle: bool = True, refine=None) -> None:
    """The estimator on held-out DA2T pairs (``pairs`` {lens: folder}; the
    factory's frames through the nominal lens at the pairs' pitch, with
    noise): AbsRel against each frame's own median (the best constant) and
    against the oracle that knows the sharp frame, over the pixels whose true
    depth lies in the library's range."""
    from dcdi_core.dfd import estimate_depth
    from dcdi_core.models.dacn.data import finished_pairs
    from .dfd_refine_study import pair_inputs
    from dcdi_core.optics.lens import load_lens
    print("| lens | pairs | scenes | AbsRel | constant (median) | ratio | oracle (sharp known) | "
          "confident tiles (share) | wall s (CPU s) per frame |")
    print("|---|---|---|---|---|---|---|---|---|")
    for lens_id, folder in pairs.items():
        lens = load_lens(lens_id)
        refiner = None
        if refine:
            from dcdi_core.app.depth import refinement
            refiner, _ = refinement("auto" if refine == "shipped" else refine, lens_id, PITCH_MM)
        recs = finished_pairs(folder)
        ids = sorted(recs)[:count]
        est_all, const_all, oracle_all, tiles, conf, secs = [], [], [], [], [], []
        for pid, pair, capture, g, library in pair_inputs(folder, lens, count):
            h, w = capture.shape[:2]
            t, c = time.perf_counter(), time.process_time()
            est = estimate_depth(capture, library, g, options, refine=refiner)
            secs.append((time.perf_counter() - t, time.process_time() - c))
            depth = np.asarray(pair.depth)
            ok = np.isfinite(depth) & (depth >= library.grid.near_m) & (depth <= library.grid.far_m)
            truth = depth[ok]
            est_all.append(np.abs(est.depth_m[ok] - truth) / truth)
            const_all.append(np.abs(np.median(truth) - truth) / truth)
            s = est.info["tile_px"]
            sharp = np.nan_to_num(np.asarray(pair.target, np.float32))
            orc = oracle_tiles(sharp, lens, g, library, capture, s, distortion=False) if oracle else np.nan
            tt = np.pad(depth, ((0, -h % s), (0, -w % s)), constant_values=np.nan)[s // 2::s, s // 2::s]
            good = np.isfinite(tt) & (tt >= library.grid.near_m) & (tt <= library.grid.far_m)
            tt = np.where(good, tt, 1.0)
            oracle_all.append((np.abs(orc - tt) / tt)[good])
            tiles.append((np.abs(1.0 / est.tile_diopters - tt) / tt)[good])
            conf.append(est.tile_confidence[good])
        e, k, o = (np.concatenate(x) for x in (est_all, const_all, oracle_all))
        t, c = np.concatenate(tiles), np.concatenate(conf)
        sure = c >= 0.5
        scenes = ", ".join(sorted({recs[p].get("scene", "").split("-")[0] or "?" for p in ids}))
        print(f"| {lens_id} | {len(ids)} | {scenes} | {e.mean():.3f} | {k.mean():.3f} | {e.mean() / k.mean():.2f} | "
              f"{o.mean():.3f} | {t[sure].mean() if sure.any() else float('nan'):.3f} ({sure.mean():.0%}) | "
              f"{np.mean([x[0] for x in secs]):.1f} ({np.mean([x[1] for x in secs]):.1f}) |")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m lab depth-from-blur", description=__doc__.split("\n\n")[0])
    p.add_argument("--lenses", nargs="+", default=["mos-s1", "mos-s2"])
    p.add_argument("--scenes", nargs="+", default=["planes", "leaves"], choices=list(SCENES))
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    p.add_argument("--where", nargs="+", default=["centre", "corner"], choices=["centre", "corner"])
    p.add_argument("--pairs", action="append", default=None, metavar="LENS=DIR",
                   help="held-out DA2T pairs of a lens (dcdi dacn pairs ... --perturb 0): the table on them "
                        "instead of the synthetic one")
    p.add_argument("--count", type=int, default=1000, help="pairs per lens at most")
    p.add_argument("--set", action="append", default=[], metavar="OPTION=VALUE",
                   help="an estimator option (DepthFromBlurOptions) other than its default, e.g. temperature=10")
    p.add_argument("--no-oracle", action="store_true", help="leave out the oracle (it simulates 21 depths)")
    p.add_argument("--refine", default=None, metavar="shipped|FILE",
                   help="with the learned refinement: each lens's shipped one, or a file (default: the evidence alone)")
    a = p.parse_args(argv)
    import ast

    from dcdi_core.dfd import DepthFromBlurOptions
    options = DepthFromBlurOptions(**{k: ast.literal_eval(v) for k, v in (x.split("=", 1) for x in a.set)})
    if a.pairs:
        pairs_table(dict(x.split("=", 1) for x in a.pairs), a.count, options, oracle=not a.no_oracle,
                    refine=a.refine)
        return 0
    tables(a.lenses, a.scenes, a.seeds, a.where, a.refine, options, not a.no_oracle)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

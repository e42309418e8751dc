"""`python -m lab olf-rays`: the Omni-Lens-Field in ray space, for every
lens (docs/olf.md, "The OLF in ray space").

Every store of the Nikkor 85 mm's kernels as pixels lost the wide discs'
rims (28-35 dB); the ray map holds them because it stores where each ray
lands and deposits the rays. This store learns the ray map's values as a
function of the source, (field, 1/depth) -> the polynomials of the stop
that say where its rays land on the two sensor planes (at the design
wavelength, and each stored wavelength's difference), where they meet each
clipping surface, the chief ray and the illumination. A PSF is made as the
map's are (``psf.raymap``: any focus by the straight rays between the
planes, any stop and iris by the stop grid, any pitch by the deposit), from
the store's values at the source's own (field, depth): no grid between.

In physical units: each polynomial is taken to an orthonormal basis of the
stop (the monomials' QR on the map's fit grid), so a coefficient's error is
the RMS of the landing points' error over the pupil, in mm. The store is a
tensor Legendre polynomial of (field, 1/depth) for each value, fitted by
least squares weighed on the rays that pass each source (``fit_live``: a
vignetted source's polynomial is wild outside them). Its data are the map's
own values at random sources (``OUT/<lens>/data.npz``, made once); the
reachable disc, the usable sources and the axial illumination stay small
tables. The maps are the shipped ones (the paper's four lenses get one
built here), or built here with ``--precise-maps`` / ``--map-recipe``.

The catalogue (the default): each lens scored at ``lab raymap``'s held-out
points (refocused, stopped down with blades, each at the pitch that holds
its blur) against 512-ray traces, beside the map it learned from; a row per
lens kept in ``OUT/<lens>/row.json``. ``--time-preview`` times a 480 x 270
preview's PSFs from each lens's map and store.

    python -m lab olf-rays --out OUT [--map-recipe n_wavelengths=16] [--lens ID ...] [--seed S]

The pilot (``--points``): the Nikkor 85 mm on the pixel stores' 64 points
(the pixel-head run's ``points.npz``, histogram kernels, 128 rays), with an
MLP on the store's residual or, ``--mlp-alone``, on the values themselves.

    python -m lab olf-rays --points RUN/points.npz --seed 0 --out OUT/rays-s0 [--iters 20000] [--mlp-alone]
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from dcdi_core.psf.rayfield import SERVE_FIELDS, RayFieldMap

from .olf_frame import LENS, PILOT

# the network's inputs: field and 1/depth (as a fraction of the map's nearest) in [-1, 1], with sines and
# cosines of these multiples of pi
FREQUENCIES = (1, 2, 3, 4)
# the smooth part: Legendre polynomials of field and 1/depth up to these degrees
BASELINE_DEGREES = (8, 8)
# what --map-recipe may set (``RayMapRecipe``'s integers)
RECIPE_FIELDS = ("n_fields", "n_depths", "n_wavelengths", "degree", "chroma_degree", "clip_degree", "fit_samples")
# the stop grid (a side) on which a landing point's error is weighed where its ray passes
MASK_SAMPLES = 48


# ------------------------------------------------------------- the layout
class Layout:
    """One source's ray map values as one vector in physical units (mm):
    the engine's :class:`~dcdi_core.psf.rayfield.StopBasis` (each polynomial
    of the stop in an orthonormal basis of the stop: its error is the RMS
    landing error over the pupil), with the stop grid on which a landing
    point's error is weighed where its ray passes. ``white``/``unwhite`` go
    between the map's arrays at sources (S, ...) and (S, D)."""

    def __init__(self, rm, lens):
        from dcdi_core.optics.aiming import stop_grid
        from dcdi_core.psf.raymap import monomial_set
        from dcdi_core.psf.rayfield import StopBasis
        self.basis = b = StopBasis.of_map(rm, lens)
        r = rm.recipe
        opened, _ = rm.wide_open(lens)
        # the rays that pass, on a coarser grid of the stop: where a landing point's error counts
        self.uv_mask = stop_grid(opened, MASK_SAMPLES) / rm.stop_radius_mm
        mono_mask = monomial_set(self.uv_mask, r)
        self.Q = {key: mono_mask[key] @ b.rinv[key] for key in mono_mask}      # landing = Q @ white
        self.clip_mono = (mono_mask[r.clip_degree, 1], mono_mask[r.clip_degree, 0])
        self.clear = np.asarray(rm.clear_mm, np.float64)
        self.recipe, self.parts, self.terms, self.shapes, self.size = r, b.parts, b.terms, b.shapes, b.size

    def live(self, at: dict) -> np.ndarray:
        """(S, P) the mask grid's rays that pass at each source: inside the
        reachable disc and every clipping surface's clear aperture."""
        u, v = self.uv_mask[:, 0], self.uv_mask[:, 1]
        aim = np.asarray(at["aim"], np.float64)
        ok = u * u + v * v + aim[:, :1] * v + aim[:, 1:] <= 0.0
        co = self.clip_mono[0].shape[1]
        for k, clear in enumerate(self.clear):
            xk = at["clip"][:, k, :co] @ self.clip_mono[0].T
            yk = at["clip"][:, k, co:] @ self.clip_mono[1].T
            ok &= xk * xk + yk * yk <= clear * clear
        return ok

    def groups(self):
        """(columns, (degree, parity)): each landing polynomial's whitened
        coefficients in the vector (the sensor planes', each wavelength's
        difference)."""
        i = 0
        for n, d in self.parts[:2]:
            no, ne = self.terms[d]
            for _ in range(int(np.prod(self.shapes[n]))):
                yield np.arange(i, i + no), (d, 1)
                yield np.arange(i + no, i + no + ne), (d, 0)
                i += no + ne

    def white(self, at: dict) -> np.ndarray:
        """(S, D) from the map's arrays at S sources."""
        return self.basis.white(at)

    def unwhite(self, vec: np.ndarray) -> dict:
        """The map's arrays at S sources from (S, D)."""
        return self.basis.unwhite(vec)


# -------------------------------------------------------------- the data
def map_values(rm, fields, diopters) -> dict:
    """The ray map's arrays at sources (fields (S,), diopters (S,)), as its
    own serving interpolates them (Lagrange in 1/depth, then in field), and
    whether every node they lean on is usable."""
    from dcdi_core.psf.raymap import grid_weights
    names = ("xy", "chroma", "clip", "chief", "geometry")
    out = {n: [] for n in names + ("ok", "aim")}
    nf = len(rm.fields)
    for f, d in zip(np.asarray(fields, np.float64), np.asarray(diopters, np.float64)):
        at = rm._interpolated(float(d))
        (idx,), (w,) = grid_weights(np.array([f * (nf - 1)]), nf)
        for n in names:
            out[n].append(np.tensordot(w, np.asarray(at[n], np.float64)[idx], axes=1))
        out["ok"].append(bool(at["ok"][idx].all()))
        (i2,), (w2,) = grid_weights(np.array([f * (nf - 1)]), nf, nodes=2)     # the reachable disc: linear
        out["aim"].append(w2 @ at["aim"][i2])
    return {n: np.asarray(v) for n, v in out.items()}


def draw_sources(rng, n: int, max_diopters: float) -> tuple[np.ndarray, np.ndarray]:
    """n sources uniform in field and in 1/depth over the map's range."""
    return rng.uniform(0.0, 1.0, n), rng.uniform(0.0, max_diopters, n)


def features(fields, diopters, max_diopters: float) -> np.ndarray:
    """(S, 2 + 4 x len(FREQUENCIES)) the network's inputs."""
    a = 2.0 * np.asarray(fields, np.float64) - 1.0
    b = 2.0 * np.asarray(diopters, np.float64) / max_diopters - 1.0
    cols = [a, b]
    for k in FREQUENCIES:
        cols += [np.sin(math.pi * k * a), np.cos(math.pi * k * a), np.sin(math.pi * k * b), np.cos(math.pi * k * b)]
    return np.stack(cols, axis=1)


def legendre_terms(fields, diopters, max_diopters: float, degrees=BASELINE_DEGREES) -> np.ndarray:
    """(S, (df + 1)(dd + 1)) tensor Legendre polynomials of field and 1/depth (the engine's)."""
    from dcdi_core.psf.rayfield import legendre_terms as terms
    return terms(fields, diopters, max_diopters, degrees)


def make_data(rm, lens, layout: Layout, seed: int, n_train: int, n_val: int, out: Path, log=print) -> dict:
    """Training and validation sources and their whitened values (``OUT/data.npz``, made once; refused where
    it was made with other settings)."""
    from dcdi_core.errors import CheckpointMismatchError
    settings = json.dumps({"lens": lens.id, "map": rm.meta["lens_fingerprint"], "seed": seed, "train": n_train,
                           "val": n_val, "mask": MASK_SAMPLES,
                           "map_dtypes": [str(rm.arrays[k].dtype) for k in ("xy", "chroma", "clip")]}, sort_keys=True)
    cache = out / "data.npz"
    if cache.exists():
        with np.load(cache) as z:
            if str(z["settings"]) != settings:
                was, now = json.loads(str(z["settings"])), json.loads(settings)
                raise CheckpointMismatchError(cache, {k: (was.get(k), now.get(k)) for k in set(was) | set(now)
                                                      if was.get(k) != now.get(k)})
            return {k: z[k] for k in z.files if k != "settings"}
    rng = np.random.default_rng(seed)
    d_max = float(rm.diopters[0])
    data = {}
    t0 = time.perf_counter()
    for part, n in (("train", n_train), ("val", n_val)):
        f, d = draw_sources(rng, n, d_max)
        v = map_values(rm, f, d)
        ok = v["ok"]
        data[f"{part}_f"], data[f"{part}_d"], data[f"{part}_y"] = f[ok], d[ok], layout.white(v)[ok]
        data[f"{part}_live"] = np.packbits(layout.live(v)[ok], axis=1)
    log(f"data: {len(data['train_f'])} + {len(data['val_f'])} sources in {time.perf_counter() - t0:.1f} s")
    out.mkdir(parents=True, exist_ok=True)
    tmp = out / "data.tmp.npz"
    np.savez(tmp, settings=settings, **data)
    tmp.replace(cache)
    return data


# ----------------------------------------------------------- the network
class RayField:
    """The learned store: baseline coefficients (T, D), the MLP's layers
    [(W (out, in), b (out,))] and its output scale; evaluated in numpy."""

    def __init__(self, baseline: np.ndarray, layers: list, scale: float, max_diopters: float):
        self.baseline, self.layers, self.scale, self.max_diopters = baseline, layers, float(scale), max_diopters

    def __call__(self, fields, diopters) -> np.ndarray:
        base = legendre_terms(fields, diopters, self.max_diopters) @ self.baseline
        if not self.layers:
            return base
        h = features(fields, diopters, self.max_diopters)
        for i, (w, b) in enumerate(self.layers):
            h = h @ w.T.astype(np.float64) + b
            if i < len(self.layers) - 1:
                h = h / (1.0 + np.exp(-h))          # SiLU
        return base + self.scale * h

    @property
    def floats(self) -> int:
        return int(self.baseline.size + sum(w.size + b.size for w, b in self.layers))


def fit_baseline(f, d, y, max_diopters: float) -> np.ndarray:
    """Least-squares Legendre coefficients (T, D) of the values y (S, D)."""
    c, *_ = np.linalg.lstsq(legendre_terms(f, d, max_diopters), y, rcond=None)
    return c.astype(np.float32).astype(np.float64)


def fit_live(layout: Layout, f, d, y, live, max_diopters: float, degrees=BASELINE_DEGREES,
             chunk: int = 256) -> np.ndarray:
    """The Legendre coefficients (T, D) where each landing polynomial is
    fitted where its rays pass (a ray the lens stops can land anywhere: a
    partly vignetted source's polynomial is wild outside the rays that pass,
    and a kink of the map's grid, not of the lens): for every source s, the
    landing points' error weighed on the stop grid's passing rays,
    sum_s |diag(live_s) Q (phi_s C - y_s)|^2, by its normal equations. The
    other values (clipping surfaces, chief ray, illumination) by plain least
    squares."""
    phi = legendre_terms(f, d, max_diopters, degrees)                      # (S, T)
    c, *_ = np.linalg.lstsq(phi, y, rcond=None)
    s_, t = phi.shape
    by_key: dict = {}
    for cols, key in layout.groups():
        by_key.setdefault(key, []).append(cols)
    for key, cols in by_key.items():
        q = layout.Q[key]                                                   # (P, n)
        n = q.shape[1]
        p = len(q)
        # sources whose every ray passes weigh the whole stop alike: one term for all of them
        full = live.all(axis=1)
        g0 = q.T @ q / p
        pf = phi[full]
        a = ((pf.T @ pf)[:, :, None, None] * g0[None, None]).reshape(t * t, n * n)    # (T, T, n, n)
        rhs = np.stack([pf.T @ (y[full][:, cc] @ g0) for cc in cols])                  # (groups, T, n)
        part = np.flatnonzero(~full)
        for s0 in range(0, len(part), chunk):
            at = part[s0:s0 + chunk]
            lv = live[at].astype(np.float64)                                # (s, P)
            h = (q.T[None] * lv[:, None, :]) @ q / p                         # (s, n, n)
            ph = phi[at]
            a += (ph[:, :, None] * ph[:, None, :]).reshape(len(ph), -1).T @ h.reshape(len(ph), -1)
            for g, cc in enumerate(cols):
                rhs[g] += ph.T @ np.einsum("sij,sj->si", h, y[at][:, cc])
        big = a.reshape(t, t, n, n).transpose(0, 2, 1, 3).reshape(t * n, t * n)
        big[np.diag_indices_from(big)] += 1e-12 * np.trace(big) / len(big)
        sol = np.linalg.solve(big, rhs.reshape(len(cols), -1).T)           # (T n, groups)
        for g, cc in enumerate(cols):
            c[:, cc] = sol[:, g].reshape(t, n)
    return c.astype(np.float32).astype(np.float64)


def live_rms_um(layout: Layout, pred, y, live) -> float:
    """The landing points' RMS error (um) over the rays that pass, every
    landing polynomial and source."""
    err, count = 0.0, 0.0
    for cols, key in layout.groups():
        e = layout.Q[key] @ (pred[:, cols] - y[:, cols]).T                 # (P, S)
        err += float((e * e * live.T).sum())
        count += float(live.sum())
    return math.sqrt(err / max(count, 1.0)) * 1000.0


def rms_um(pred, y) -> float:
    """The RMS error over sources and outputs, um (outputs are mm)."""
    return float(np.sqrt(np.mean((pred - y) ** 2)) * 1000.0)


def train(data: dict, max_diopters: float, seed: int, iters: int, width: int, layers: int, lr: float,
          batch: int = 1024, every: int = 1000, checkpoint=None, base=None, log=print) -> tuple[RayField, list, float]:
    """The baseline, then the MLP on its residual: the store, the learning
    curve (training and validation RMS, um) and its CPU seconds.
    ``checkpoint(step, store)`` is called at every curve point."""
    import torch

    from .olf_basis import fit_steps, mlp
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed + 1)
    if base is None:
        base = fit_baseline(data["train_f"], data["train_d"], data["train_y"], max_diopters)

    def residual(part):
        return data[f"{part}_y"] - legendre_terms(data[f"{part}_f"], data[f"{part}_d"], max_diopters) @ base
    rt, rv = residual("train"), residual("val")
    scale = float(np.sqrt(np.mean(rt ** 2))) or 1.0
    net, ema = mlp(features([0.0], [0.0], 1.0).shape[1], rt.shape[1], width, layers)
    with torch.no_grad():           # it starts as the Legendre fit (the EMA's first update copies it)
        net[-1].weight.zero_(), net[-1].bias.zero_()
    xt = torch.from_numpy(features(data["train_f"], data["train_d"], max_diopters)).float()
    yt = torch.from_numpy(rt / scale).float()

    def store(model) -> RayField:
        lin = [m for m in model.modules() if isinstance(m, torch.nn.Linear)]
        return RayField(base, [(m.weight.detach().float().numpy().copy(), m.bias.detach().float().numpy().astype(
            np.float64)) for m in lin], scale, max_diopters)
    curve = [{"step": 0, "train_um": rms_um(0.0, rt), "val_um": rms_um(0.0, rv)}]
    log(f"before the MLP: validation RMS {curve[0]['val_um']:.3f} um")
    t0, paused = time.process_time(), 0.0
    for step, loss in fit_steps(net, ema, xt, yt, rng, iters, lr, batch, every):
        s = store(ema.module)
        pv = s(data["val_f"], data["val_d"]) - legendre_terms(data["val_f"], data["val_d"], max_diopters) @ base
        curve.append({"step": step, "train_um": math.sqrt(loss) * scale * 1000.0,
                      "val_um": rms_um(pv, rv), "cpu_s": time.process_time() - t0 - paused})
        log(f"step {step}: train {curve[-1]['train_um']:.3f} um, validation {curve[-1]['val_um']:.3f} um")
        if checkpoint:          # its scoring is not the training's time
            t1 = time.process_time()
            checkpoint(step, s)
            paused += time.process_time() - t1
    return store(ema.module), curve, time.process_time() - t0 - paused


# ------------------------------------------------------------- serving
def neural_map(rm, lens, layout: Layout, predict, n_fields: int = SERVE_FIELDS):
    """A ray map served as the engine serves a ray-space OLF
    (``psf.rayfield.RayFieldMap``) whose values at sources are ``predict(fields,
    diopters) -> (S, D)`` (whitened, :class:`Layout`) at ``n_fields`` fields:
    an MLP's, or the map's own (:func:`exact_predict`)."""
    class NeuralRayMap(RayFieldMap):
        def values(self, fields, diopters):
            return layout.unwhite(predict(fields, diopters))
    nm = NeuralRayMap.of_fit(rm, layout.basis, np.zeros((1, layout.size)), (0, 0), float(rm.diopters[0]))
    nm.fields = np.linspace(0.0, 1.0, n_fields)
    return nm


def exact_predict(rm, layout: Layout):
    """``predict`` that gives the ray map's own values (the oracle: a network with no error)."""
    def predict(fields, diopters):
        return layout.white(map_values(rm, fields, diopters))
    return predict


# --------------------------------------------------------------- scoring
def held_out(points: Path, seed: int) -> dict:
    """{label: (lens, settings, field, depth_m, focus_m, traced kernels)}: the
    pixel-head run's held-out points (wide open, across focus)."""
    from dcdi_core.models.olf.data import PSFDataConfig
    from dcdi_core.optics.lens import load_lens
    lens = load_lens(LENS)
    with np.load(points) as z:
        p = {k: z[k] for k in z.files}
    y = p[f"{LENS}.val.y"]
    f, d, fm = p[f"{LENS}.val.field"], p[f"{LENS}.val.depth_m"], p[f"{LENS}.val.focus_m"]
    config = PSFDataConfig(seed=seed, **PILOT)
    s = replace(config.psf_settings(int(y.shape[-1])), pupil_samples=config.held_out_rays)
    return {"wide open": (lens, s, f, d, fm, y)}


def scores(rm, sets: dict, rays: int) -> dict:
    """{label: psf_scores} of ``rm``'s PSFs, with ``rays`` a side, at each set's points."""
    from dcdi_core.models.common.metrics import psf_scores
    from dcdi_core.models.olf.data import raymap_points
    out = {}
    for label, (lens, s, f, d, fm, y) in sets.items():
        psf, ok = raymap_points(rm, lens, replace(s, pupil_samples=int(rays)), f, d, fm)
        live = ok & (y.sum(axis=(1, 2, 3)) > 0)
        out[label] = {"n": int(live.sum()), **psf_scores(psf[live], y[live], scale="sum")}
    return out


def run_pilot(points: Path, seed: int, out: Path, *, iters: int = 20000, width: int = 256,
              layers: int = 3, lr: float = 1e-3, rays: int = 128, n_train: int = 16384, n_val: int = 2048,
              every: int = 1000, score_every: int = 5000, with_baseline: bool = True, log=print) -> dict:
    """The Nikkor 85 mm pilot on the pixel stores' points (module docstring)."""
    import torch
    from dcdi_core.optics.lens import load_lens
    from dcdi_core.psf.raymap import open_raymap
    from dcdi_core.shipped import raymap_file
    torch.set_num_threads(1)
    out.mkdir(parents=True, exist_ok=True)
    lens = load_lens(LENS)
    rm = open_raymap(raymap_file(LENS))
    layout = Layout(rm, lens)
    d_max = float(rm.diopters[0])
    data = make_data(rm, lens, layout, seed, n_train, n_val, out, log=log)
    sets = held_out(points, seed)
    result = {"lens": LENS, "seed": seed, "rays": rays, "mlp_on": "the Legendre fit's residual" if with_baseline
              else "the values (no Legendre fit)", "outputs": layout.size, "train_sources": len(data["train_f"]),
              "points": {k: int(len(v[2])) for k, v in sets.items()},
              "ray_map": scores(rm, sets, rays), "ray_map_mb": _map_mb(rm)}
    result["oracle"] = scores(neural_map(rm, lens, layout, exact_predict(rm, layout)), sets, rays)
    for k, v in result["ray_map"].items():
        log(f"ray map, {k}: {_spread(v)}; the map's values at {SERVE_FIELDS} fields: {_spread(result['oracle'][k])}")
    curve_scores = []

    def checkpoint(step, s):
        if step % score_every == 0 or step == iters:
            sc = scores(neural_map(rm, lens, layout, s), sets, rays)
            curve_scores.append({"step": step, **{k: v["psnr_8bit"] for k, v in sc.items()}})
            log(f"step {step}: " + ", ".join(f"{k} {v['psnr_8bit']:.2f} dB" for k, v in sc.items()))
    live = {part: np.unpackbits(data[f"{part}_live"], axis=1, count=len(layout.uv_mask)).astype(bool)
            for part in ("train", "val")}
    base = fit_live(layout, data["train_f"], data["train_d"], data["train_y"], live["train"], d_max)

    def val_um(model):
        return live_rms_um(layout, model(data["val_f"], data["val_d"]), data["val_y"], live["val"])
    legendre = RayField(base, [], 0.0, d_max)
    result["baseline"] = scores(neural_map(rm, lens, layout, legendre), sets, rays)
    result["baseline_live_um"] = val_um(legendre)
    log(f"baseline {BASELINE_DEGREES}: " + ", ".join(f"{k} {_spread(v)}" for k, v in result["baseline"].items()))
    if iters:
        store, curve, cpu = train(data, d_max, seed, iters, width, layers, lr, every=every, checkpoint=checkpoint,
                                  base=base if with_baseline else np.zeros_like(base),
                                  log=log)
        result.update(network=scores(neural_map(rm, lens, layout, store), sets, rays), network_live_um=val_um(store),
                      curve=curve,
                      curve_psnr=curve_scores, cpu_s=cpu, iterations=iters, width=width, layers=layers, lr=lr,
                      floats=store.floats, megabytes=4 * (store.floats + _table_floats(rm)) / 1e6)
        np.savez(out / "store.npz", baseline=store.baseline.astype(np.float32), scale=store.scale,
                 **{f"w{i}": w for i, (w, _) in enumerate(store.layers)},
                 **{f"b{i}": b.astype(np.float32) for i, (_, b) in enumerate(store.layers)})
    (out / "result.json").write_text(json.dumps(result, indent=1, default=float) + "\n")
    return result


# ------------------------------------------------------------- catalogue
def lens_map(lens, out: Path, precise: bool = False, recipe: dict | None = None, log=print):
    """The lens's shipped ray map, or one built here once with the shipped
    maps' recipe (``OUT/maps/<lens>.npz``: the paper's lenses ship none);
    ``precise``: built here for every lens, its fits kept in float64
    (``OUT/maps/<lens>-f64.npz``: a shipped map's chromatic differences are
    float16, 0.01-0.15 um); ``recipe``: built so with these ``RayMapRecipe``
    fields (and in float64), ``OUT/maps/<lens>-<fields>.npz``."""
    from dcdi_core.psf.raymap import RayMap, RayMapRecipe, build, open_raymap
    from dcdi_core.shipped import raymap_file
    path = raymap_file(lens.id)
    if path is not None and not (precise or recipe):
        return open_raymap(path), True
    tag = "".join(f"-{k}{v}" for k, v in sorted((recipe or {}).items())) or "-f64"
    path = out / "maps" / f"{lens.id}{tag if precise or recipe else ''}.npz"
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()
        rm = build(lens, RayMapRecipe(**(recipe or {})), precise=bool(precise or recipe))
        tmp = path.with_suffix(".tmp.npz")
        rm.save(tmp)
        tmp.replace(path)
        log(f"{lens.id}: ray map built in {time.perf_counter() - t0:.0f} s (none ships)")
    return RayMap.load(path), False


def references(lens, n_points: int, seed: int, rays: int, out: Path, log=print) -> list[dict]:
    """``lab raymap``'s held-out points of the lens (the same draw: refocused, stopped down with blades, each
    at the finest pitch whose 129 px kernel holds its blur), their traces with ``rays`` a side and the
    paper's Gaussian (``OUT/<lens>/points.npz``, made once)."""
    import zlib
    import warnings

    from dcdi_core.psf.compute import KernelTooSmallWarning, PSFSettings, psf

    from .raymap_report import KERNEL, SIGMA_PX, _lens_at, _pitch_for, draw_points
    cache = out / lens.id / "points.npz"
    key = json.dumps({"points": n_points, "seed": seed, "rays": rays, "sigma": SIGMA_PX}, sort_keys=True)
    if cache.exists():
        with np.load(cache) as z:
            if str(z["key"]) == key:
                pts = json.loads(str(z["points"]))
                for p, k in zip(pts, z["kernels"]):
                    p["reference"] = k
                return pts
    pts = draw_points(lens, n_points, seed + zlib.crc32(lens.id.encode()) % 10007)
    t0 = time.perf_counter()
    for p in pts:
        at = _lens_at(lens, p)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", KernelTooSmallWarning)
            p["pitch_mm"] = _pitch_for(at, p)
            p["reference"] = psf(at, depth_m=p["depth_m"], field=p["field"],
                                 settings=_point_settings(p, rays, KERNEL, SIGMA_PX)).psf
    log(f"{lens.id}: {n_points} points traced with {rays} rays in {time.perf_counter() - t0:.0f} s")
    cache.parent.mkdir(parents=True, exist_ok=True)
    tmp = cache.with_suffix(".tmp.npz")
    np.savez(tmp, key=key, points=json.dumps([{k: v for k, v in p.items() if k != "reference"} for p in pts]),
             kernels=np.stack([p["reference"] for p in pts]))
    tmp.replace(cache)
    return pts


def _point_settings(p: dict, rays: int, kernel: int, sigma: float):
    from dcdi_core.psf.compute import PSFSettings
    return PSFSettings(kernel_size=kernel, pupil_samples=rays, pixel_pitch_mm=p["pitch_mm"],
                       focus_distance_m=p["focus_m"], deposit_sigma_px=sigma)


def lens_study(lens_id: str, out: Path, *, seed: int = 0, n_points: int = 8, rays: int = 512, n_train: int = 2048,
               n_val: int = 1024, precise: bool = False, recipe: dict | None = None, log=print) -> dict:
    """One catalogue lens: its ray-space OLF (the Legendre store) fitted to
    its ray map, and both scored with the same rays as the reference trace
    at ``lab raymap``'s held-out points: against the trace, and against the
    map (the store's own error)."""
    import warnings

    from dcdi_core.optics.lens import load_lens
    from dcdi_core.psf.compute import KernelTooSmallWarning

    from .raymap_report import KERNEL, SIGMA_PX, _lens_at, _map_kernel, _psnr
    # a lens's row is kept (OUT/<lens>/row.json) with every setting that made it: a run over the catalogue
    # after runs over parts of it scores nothing twice
    key = {"seed": seed, "points": n_points, "rays": rays, "train": n_train, "val": n_val,
           "degrees": list(BASELINE_DEGREES), "mask": MASK_SAMPLES, "precise": precise,
           **({"recipe": recipe} if recipe else {})}
    precise = precise or bool(recipe)
    kept = out / lens_id / "row.json"
    if kept.exists():
        was = json.loads(kept.read_text())
        # (rows of this study's first runs also say iters 0: no MLP; an MLP's row is not this one)
        old = {k: v for k, v in was.get("key", {}).items() if k not in ("iters", "width", "layers", "lr")}
        if old == key and not was["key"].get("iters"):
            was["map_mb"] = _map_mb(lens_map(load_lens(lens_id), out, precise, recipe, log=log)[0])
            return was
    lens = load_lens(lens_id)
    rm, shipped = lens_map(lens, out, precise, recipe, log=log)
    layout = Layout(rm, lens)
    d_max = float(rm.diopters[0])
    data = make_data(rm, lens, layout, seed, n_train, n_val, out / lens_id, log=log)
    live = {part: np.unpackbits(data[f"{part}_live"], axis=1, count=len(layout.uv_mask)).astype(bool)
            for part in ("train", "val")}
    t0 = time.process_time()
    base = fit_live(layout, data["train_f"], data["train_d"], data["train_y"], live["train"], d_max)
    fit_s = time.process_time() - t0
    np.savez(out / lens_id / "store.npz", legendre=base.astype(np.float32), degrees=np.array(BASELINE_DEGREES),
             max_diopters=d_max)
    plain = fit_baseline(data["train_f"], data["train_d"], data["train_y"], d_max)
    store = RayField(base, [], 0.0, d_max)

    def val_um(model):
        return live_rms_um(layout, model(data["val_f"], data["val_d"]), data["val_y"], live["val"])
    row = {"lens": lens_id, "map_shipped": shipped, "map_mb": _map_mb(rm), "outputs": layout.size, "fit_cpu_s": fit_s,
           "plain_fit_um": val_um(RayField(plain, [], 0.0, d_max))}
    row["store_val_um"] = val_um(store)
    row["store_mb"] = 4 * (store.floats + _table_floats(rm)) / 1e6
    nm = RayFieldMap.of_fit(rm, layout.basis, base, BASELINE_DEGREES, d_max)         # as it ships
    pts = references(lens, n_points, seed, rays, out, log=log)
    ships = lens_map(lens, out, log=log)[0] if precise and shipped is False and _ships(lens_id) else None
    t0 = time.perf_counter()
    for p in pts:
        at = _lens_at(lens, p)
        s = _point_settings(p, rays, KERNEL, SIGMA_PX)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", KernelTooSmallWarning)
            m = _map_kernel(rm, at, p, s)
            o = _map_kernel(nm, at, p, s)
            if ships is not None:
                p["shipped_map"] = _psnr(_map_kernel(ships, at, p, s), p["reference"])
        p.update(map=_psnr(m, p["reference"]), olf=_psnr(o, p["reference"]), olf_vs_map=_psnr(o, m))
        del p["reference"]
    row["points"] = pts
    for k in ("map", "olf", "olf_vs_map") + (("shipped_map",) if ships is not None else ()):
        v = np.array([p[k] for p in pts])
        row[k] = (float(v.mean()), float(v.min()))
    log(f"{lens_id}: store {row['store_val_um']:.4f} um RMS from the map's passing rays (plain least squares "
        f"{row['plain_fit_um']:.4f}), {row['store_mb']:.2f} MB; against the "
        f"{rays}-ray trace: map {row['map'][0]:.2f} ({row['map'][1]:.2f}), OLF {row['olf'][0]:.2f} "
        f"({row['olf'][1]:.2f}) dB; OLF against the map {row['olf_vs_map'][0]:.2f} ({row['olf_vs_map'][1]:.2f}) dB "
        f"[{time.perf_counter() - t0:.0f} s]")
    row["key"] = key
    kept.write_text(json.dumps(row, default=float) + "\n")
    return json.loads(kept.read_text())


def export(path: Path, rows: list[dict], out: Path, command: str, log=print) -> Path:
    """The studied lenses' stores (``OUT/<lens>/store.npz``) as one OLF file in ray space, each lens with the
    map it learned from and its held-out scores."""
    from dcdi_core.optics.lens import load_lens
    from dcdi_core.psf.rayfield import RayFieldOLF, StopBasis
    items = []
    for r in rows:
        lens, key = load_lens(r["lens"]), r["key"]
        rm, shipped = lens_map(lens, out, key["precise"], key.get("recipe"), log=log)
        with np.load(out / r["lens"] / "store.npz") as z:
            coeffs, degrees, d_max = z["legendre"], tuple(int(v) for v in z["degrees"]), float(z["max_diopters"])
        held = {"points": key["points"], "seed": key["seed"], "rays": key["rays"], "psnr_8bit": list(r["olf"]),
                "map_psnr_8bit": list(r["map"]), "against_map_psnr_8bit": list(r["olf_vs_map"]),
                "map": "shipped" if shipped else "built here" + "".join(
                    f", {k} {v}" for k, v in sorted((key.get("recipe") or {}).items())),
                "landing_rms_um": r["store_val_um"]}
        items.append((rm, StopBasis.of_map(rm, lens), coeffs, degrees, d_max, held))
    path.parent.mkdir(parents=True, exist_ok=True)
    RayFieldOLF.write(path, items, {"training": {"command": command, "train_sources": rows[0]["key"]["train"],
                                                 "seed": rows[0]["key"]["seed"], "fit": "least squares on the "
                                                 "rays that pass each source (lab/olf_rays.py fit_live)"}})
    return path


def against_basis(lens_id: str, olf_file: Path, out: Path, n_points: int, log=print) -> dict:
    """The lens's shipped PSF basis and the OLF in ray space at the same
    points: ``lab report psf-source``'s off-grid draw at the basis's pitch,
    kernel and focus (prescribed, wide open: all a basis holds), against its
    1024-ray references (``OUT/references-<lens>.npz``, made once); the OLF's
    kernels deposited with the references' rays."""
    import warnings

    from dcdi_core.optics.lens import load_lens
    from dcdi_core.psf.basis import SHIPPED_RECIPES, BasisLibrary, open_store, shipped_store
    from dcdi_core.psf.compute import KernelTooSmallWarning
    from dcdi_core.psf.raymap import RayMapLibrary
    from dcdi_core.psf.rayfield import RayFieldOLF

    from .psf_source_report import REF_RAYS, REPORT_SEED, pad_to, references, summary
    lens, recipe = load_lens(lens_id), SHIPPED_RECIPES[lens_id]
    settings = replace(recipe.settings(lens), pupil_samples=REF_RAYS)
    f, d, ref = references(lens, settings, recipe.grid, n_points, REPORT_SEED, out, log)
    k = recipe.kernel_size
    basis_path = shipped_store(lens_id)
    basis = BasisLibrary(open_store(basis_path), lens).at(f, d)
    lib = RayMapLibrary(RayFieldOLF.load(olf_file).map_for(lens_id), lens, settings, recipe.grid)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", KernelTooSmallWarning)
        olf = np.stack([lib.kernels(fi, di) for fi, di in zip(f, d)])
    row = {"lens": lens_id, "points": int(len(f)), "pixel_pitch_mm": settings.pixel_pitch_mm, "kernel": k,
           "basis": summary(pad_to(basis, k), ref), "olf": summary(pad_to(olf, k), ref),
           "basis_mb": basis_path.stat().st_size / 1e6}
    net = _network(lens, settings.pixel_pitch_mm)
    if net is not None:             # the OLF network where it serves these points (its kernels cropped to k)
        row["network"] = summary(pad_to(net.kernels(f, d, dtype=np.float64), k), ref)
    log(("" if net is None else f"{lens_id}: the OLF network {row['network']['psnr_8bit']:.2f} "
         f"({row['network']['psnr_8bit_worst']:.2f}) dB\n")
        + f"{lens_id}: at the basis's {len(f)} points ({settings.pixel_pitch_mm * 1000:.3g} um, {k} px, against "
        f"{REF_RAYS}-ray traces): basis {row['basis']['psnr_8bit']:.2f} ({row['basis']['psnr_8bit_worst']:.2f}), "
        f"OLF in ray space {row['olf']['psnr_8bit']:.2f} ({row['olf']['psnr_8bit_worst']:.2f}) dB")
    return row


def _network(lens, pitch_mm: float):
    """The shipped OLF network's library of ``lens`` at ``pitch_mm``, or None where it does not serve it."""
    from dcdi_core.errors import DcdiError
    from dcdi_core.psf.olf import OmniLensField
    from dcdi_core.psf.sources import SHIPPED, OLFLibrary
    try:
        return OLFLibrary(OmniLensField.load(SHIPPED), lens, pixel_pitch_mm=pitch_mm)
    except (DcdiError, OSError):
        return None


PREVIEW_PX = (270, 480)


def stored(lens_id: str, out: Path, log=print):
    """(lens, the map that serves it today (shipped, or built here with the
    shipped recipe), the map served from the store ``OUT/<lens>/store.npz``
    that a study wrote, with the map it learned from)."""
    from dcdi_core.optics.lens import load_lens
    lens = load_lens(lens_id)
    key = json.loads((out / lens_id / "row.json").read_text())["key"]
    rm, _ = lens_map(lens, out, key["precise"], key.get("recipe"), log=log)
    with np.load(out / lens_id / "store.npz") as z:
        nm = RayFieldMap.of_fit(rm, Layout(rm, lens).basis, z["legendre"], tuple(z["degrees"]), float(z["max_diopters"]))
    return lens, lens_map(lens, out, log=log)[0], nm


def preview_seconds(rm, nm, lens, repeat: int = 3) -> dict:
    """Wall seconds (best of ``repeat``, one thread) of a 480 x 270 preview's
    PSFs at its pitch with the preview's rays and wavelengths
    (``psf.sources.PREVIEW_TRACE``): one depth bin of the library's 64 fields
    (what a focus change makes per depth the scene holds) and the whole
    library (21 bins), from the ray map and from the store."""
    from dcdi_core.parallel import one_blas_thread
    from dcdi_core.psf.compute import PSFSettings
    from dcdi_core.psf.library import LibraryGrid
    from dcdi_core.psf.raymap import RayMapLibrary
    from dcdi_core.psf.sources import PREVIEW_TRACE
    pitch = 2.0 * lens.sensor.semi_diagonal_mm / math.hypot(*PREVIEW_PX)
    s = replace(PSFSettings(pixel_pitch_mm=pitch), **PREVIEW_TRACE)
    out = {"pitch_mm": pitch}
    for name, m in (("map", rm), ("olf", nm)):
        one, whole = [], []
        for _ in range(repeat):
            m._depths.clear()
            lib = RayMapLibrary(m, lens, s, LibraryGrid())
            with one_blas_thread():
                t = time.perf_counter()
                lib._compute([len(lib.depths_m) // 2], None)
                one.append(time.perf_counter() - t)
                m._depths.clear()
                lib = RayMapLibrary(m, lens, s, LibraryGrid())
                t = time.perf_counter()
                lib._compute(list(range(len(lib.depths_m))), None)
                whole.append(time.perf_counter() - t)
        out[name] = {"one_bin_s": min(one), "library_s": min(whole)}
    return out


def preview_job_seconds(lens, focus_m: float | None = 1.5, repeat: int = 3, source: str = "olf",
                        olf_file=None) -> dict:
    """Wall seconds (best of ``repeat``, one thread) of the PSFs of the
    add-on's 480 x 270 viewport preview (``blender_addon.logic.run_bokeh``'s
    request: its field step, focus tolerance and preview budget) from
    ``source``, each from a cold source: a scene from 0.8 m to a wall at
    10 m, the lens focused at ``focus_m`` (None: as prescribed, kept at 1.5 m); ``olf_file``: the OLF
    file (None: the shipped ones)."""
    from dcdi_core import app
    from dcdi_core.app.sources import SourceCache
    from dcdi_core.parallel import one_blas_thread
    h, w = PREVIEW_PX
    rng = np.random.default_rng(0)
    image = rng.random((h, w, 3), dtype=np.float32)
    depth = np.broadcast_to(np.geomspace(0.8, 10.0, w, dtype=np.float32), (h, w)).copy()
    psf = app.PSFRequest(source=source, olf_file=None if olf_file is None else str(olf_file), preview=True, field_step_px=16.0, focus_tolerance_px=0.25,
                         max_error_db=app.DEFAULT_BUDGET_DB["preview"])
    keep = (focus_m or 1.5) * 0.97, (focus_m or 1.5) * 1.03
    request = app.BokehRequest(image, depth, lens, keep=keep, focus_m=focus_m,
                               render=app.RenderRequest(lens, patch=16), psf=psf, image_name="the preview")
    best = {}
    for _ in range(repeat):
        with one_blas_thread():
            r = app.bokeh(request, cache=SourceCache())
        for k, v in r.seconds.items():
            best[k] = min(best.get(k, math.inf), float(v))
    return {"seconds": best, "source": r.source.message if hasattr(r.source, "message") else str(r.source),
            "plan": (r.info.get("quality") or {}).get("plan")}


def catalogue_table(rows: list[dict], rays: int) -> str:
    """The table of docs/olf.md: per lens and over all, PSNR mean (worst)."""
    shipped = any("shipped_map" in r for r in rows)
    out = [f"| lens | map learned from, MB | OLF MB | OLF vs map, um RMS | against the {rays}-ray trace: "
           + ("shipped map | " if shipped else "") + "map learned from | OLF | OLF against the map it learned |",
           "|---|---|---|---|---|---|---|" + ("---|" if shipped else "")]

    def pair(v):
        return "" if v is None else f"{v[0]:.2f} ({v[1]:.2f})"
    for r in rows:
        out.append(f"| `{r['lens']}`{'' if r['map_shipped'] else ' (built here)'} | {r['map_mb']:.2f} | "
                   f"{r['store_mb']:.2f} | {r['store_val_um']:.4f} | "
                   + (f"{pair(r.get('shipped_map')) or 'none ships'} | " if shipped else "")
                   + f"{pair(r['map'])} | {pair(r['olf'])} | {pair(r['olf_vs_map'])} |")
    allp = [p for r in rows for p in r["points"]]

    def both(k):
        v = np.array([p[k] for p in allp if k in p])
        return f"{v.mean():.2f} ({v.min():.2f})"
    out.append(f"| all {len(rows)} lenses, {len(allp)} points | {sum(r['map_mb'] for r in rows):.2f} | "
               f"{sum(r['store_mb'] for r in rows):.2f} | {max(r['store_val_um'] for r in rows):.4f} (largest) | "
               + (f"{both('shipped_map')} | " if shipped else "")
               + f"{both('map')} | {both('olf')} | {both('olf_vs_map')} |")
    return "\n".join(out)


def _ships(lens_id: str) -> bool:
    from dcdi_core.shipped import raymap_file
    return raymap_file(lens_id) is not None


def _map_mb(rm) -> float:
    """The map's file, MB (as it ships)."""
    return Path(rm.path).stat().st_size / 1e6


def _table_floats(rm) -> int:
    return int(rm.arrays["aim"].size + rm.arrays["ok"].size + rm.arrays["reference_geometry"].size)


def _spread(sc: dict) -> str:
    return f"mean {sc['psnr_8bit']:.2f}, median {sc['psnr_8bit_median']:.2f}, worst {sc['psnr_8bit_worst']:.2f} dB"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m lab olf-rays", description=__doc__.split("\n\n")[0])
    p.add_argument("--out", required=True, help="a folder: each lens's data, points and maps (made once), "
                                                "result.json")
    p.add_argument("--lens", action="append", default=None,
                   help="a catalogue lens (repeat; default: every lens, the paper's four with a map built here)")
    p.add_argument("--held-out", type=int, default=8, dest="n_points",
                   help="held-out points a lens, lab raymap's draw (default 8)")
    p.add_argument("--points", default=None,
                   help="instead, the Nikkor 85 mm pilot: the pixel-head run's points.npz (its held-out traces)")
    p.add_argument("--seed", type=int, default=0, help="the draw's and the network's seed (the pilot: its points' key)")
    p.add_argument("--iters", type=int, default=None,
                   help="the pilot: MLP iterations (default 20000; 0: the Legendre store alone)")
    p.add_argument("--width", type=int, default=None, help="the pilot: MLP width (default 256)")
    p.add_argument("--layers", type=int, default=None, help="the pilot: MLP hidden layers (default 3)")
    p.add_argument("--lr", type=float, default=1e-3, help="peak learning rate (default 1e-3)")
    p.add_argument("--rays", type=int, default=None,
                   help="rays a side in every scored PSF (default 512, the references'; the pilot 128)")
    p.add_argument("--train-sources", type=int, default=None,
                   help="sources of the map's values learned (default 2048; the pilot 16384)")
    p.add_argument("--mlp-alone", action="store_true",
                   help="the pilot: the MLP learns the values themselves (the paper's way), not the Legendre fit's "
                        "residual")
    p.add_argument("--precise-maps", action="store_true",
                   help="learn from ray maps built here with their fits in float64, for every lens (a shipped map "
                        "holds its chromatic differences in float16); the shipped map scored beside")
    p.add_argument("--map-recipe", action="append", default=None, metavar="FIELD=N",
                   help="learn from maps built here with this RayMapRecipe field (repeat: "
                        + ", ".join(RECIPE_FIELDS) + "; float64)")
    p.add_argument("--export", default=None, metavar="FILE",
                   help="write the lenses' stores as one OLF file in ray space (psf.rayfield; --olf FILE serves "
                        "it), each with its held-out scores")
    p.add_argument("--against-basis", default=None, metavar="OLF_FILE",
                   help="instead, score this OLF file in ray space and each of its lenses' shipped PSF basis at "
                        "the basis's points (lab report psf-source's draw, --held-out of them, 1024-ray references)")
    p.add_argument("--time-preview-job", default=None, metavar="OLF_FILE",
                   help="instead, time the PSFs of the add-on's 480 x 270 viewport preview from this OLF file for "
                        "each of its lenses (--lens: some; run on a quiet machine)")
    p.add_argument("--time-preview", action="store_true",
                   help="instead, time a 480 x 270 preview's PSFs from each lens's map and from its store (a study "
                        "into --out made it; run on a quiet machine)")
    a = p.parse_args(argv)
    out, say = Path(a.out), (lambda t: print(t, file=sys.stderr))

    def opt(v, default):
        return default if v is None else v
    if a.points:
        r = run_pilot(Path(a.points), a.seed, out, iters=opt(a.iters, 20000),
                      width=opt(a.width, 256), layers=opt(a.layers, 3), lr=a.lr, rays=opt(a.rays, 128),
                      n_train=opt(a.train_sources, 16384), with_baseline=not a.mlp_alone, log=say)
        for name in ("ray_map", "oracle", "baseline", "network"):
            for k, v in r.get(name, {}).items():
                print(f"{name}, {k} ({v['n']} points, {r['rays']} rays): {_spread(v)}")
        print(f"the Legendre store: {r['baseline_live_um']:.4f} um RMS from the map's passing rays"
              + (f"; the network {r['network_live_um']:.4f} um" if "network" in r else ""))
        if "network" in r:
            print(f"network: {r['layers']} x {r['width']}, {r['floats']} floats ({r['megabytes']:.2f} MB with its "
                  f"tables; the ray map {r['ray_map_mb']:.2f} MB), {r['iterations']} iterations, "
                  f"{r['cpu_s']:.0f} CPU s")
        return 0
    from dcdi_core.errors import DcdiError
    from dcdi_core.optics.lens import available_lenses, load_lens
    lenses = a.lens or available_lenses()
    try:
        for lid in lenses:          # every name checked before any work
            load_lens(lid)
    except DcdiError as e:
        print(f"lab: error: --lens: {e}", file=sys.stderr)
        return 2
    if a.iters or a.mlp_alone:
        # an MLP's plain loss on the weighted fit's residual would chase the values where no ray passes
        print("lab: error: --iters and --mlp-alone are the pilot's (with --points)", file=sys.stderr)
        return 2
    if a.n_points < 1 or opt(a.train_sources, 2048) < 64:
        print("lab: error: --held-out must be >= 1 and --train-sources >= 64", file=sys.stderr)
        return 2
    if a.against_basis:
        from dcdi_core.psf.basis import shipped_store
        from dcdi_core.psf.rayfield import RayFieldOLF
        held = [lid for lid in RayFieldOLF.load(a.against_basis).lens_ids if shipped_store(lid) is not None
                and (a.lens is None or lid in a.lens)]
        rows = [against_basis(lid, Path(a.against_basis), out, a.n_points, log=say) for lid in held]
        (out / "against-basis.json").write_text(json.dumps(rows, indent=1) + "\n")
        for r in rows:
            print(f"| {r['lens']} | {r['points']} | {r['pixel_pitch_mm'] * 1000:.3g} um, {r['kernel']} px | "
                  f"{r['basis_mb']:.2f} | {r['basis']['psnr_8bit']:.2f} ({r['basis']['psnr_8bit_worst']:.2f}) | "
                  f"{r['olf']['psnr_8bit']:.2f} ({r['olf']['psnr_8bit_worst']:.2f}) | "
                  + (f"{r['network']['psnr_8bit']:.2f} ({r['network']['psnr_8bit_worst']:.2f}) |" if "network" in r
                     else "does not serve |"))
        return 0
    if a.time_preview:
        times = {}
        for lid in lenses:
            lens, rm, nm = stored(lid, out, log=say)
            times[lid] = t = preview_seconds(rm, nm, lens)
            print(f"{lid}: 480 x 270 preview at {t['pitch_mm'] * 1000:.3g} um, one depth bin map "
                  f"{t['map']['one_bin_s']:.3f} / store {t['olf']['one_bin_s']:.3f} s, the library (21 bins) "
                  f"{t['map']['library_s']:.3f} / {t['olf']['library_s']:.3f} s")
        (out / "preview.json").write_text(json.dumps(times, indent=1) + "\n")
        return 0
    if a.time_preview_job:
        from dcdi_core.psf.basis import shipped_store
        from dcdi_core.psf.rayfield import RayFieldOLF
        jobs = {}
        for lid in RayFieldOLF.load(a.time_preview_job).lens_ids:
            if a.lens and lid not in a.lens:
                continue
            lens = load_lens(lid)
            olf = a.time_preview_job
            jobs[lid] = t = {"refocused": preview_job_seconds(lens, olf_file=olf),
                             "prescribed": preview_job_seconds(lens, None, olf_file=olf)}
            if shipped_store(lid) is not None:
                t["basis"] = preview_job_seconds(lens, None, source="basis")
            if _ships(lid):
                t["raymap"] = preview_job_seconds(lens, source="raymap")
            print(f"{lid}: the add-on's 480 x 270 preview, PSF seconds: OLF refocused at 1.5 m "
                  f"{t['refocused']['seconds']['psfs']:.3f}, as prescribed {t['prescribed']['seconds']['psfs']:.3f}"
                  + (f", its PSF basis as prescribed {t['basis']['seconds']['psfs']:.3f}" if "basis" in t else "")
                  + (f", its shipped ray map refocused {t['raymap']['seconds']['psfs']:.3f}" if "raymap" in t else "")
                  + f" ({t['refocused']['plan']})")
        (out / "preview-job.json").write_text(json.dumps(jobs, indent=1) + "\n")
        return 0
    rays = opt(a.rays, 512)
    recipe = {}
    for item in a.map_recipe or ():
        name, _, value = item.partition("=")
        if name not in RECIPE_FIELDS or not value.isdigit():
            print(f"lab: error: --map-recipe {item!r}: FIELD=N, FIELD one of {', '.join(RECIPE_FIELDS)}",
                  file=sys.stderr)
            return 2
        recipe[name] = int(value)
    try:
        rows = [lens_study(lid, out, seed=a.seed, n_points=a.n_points, rays=rays,
                           n_train=opt(a.train_sources, 2048), precise=a.precise_maps,
                           recipe=recipe, log=say)
                for lid in lenses]
    except DcdiError as e:
        print(f"lab: error: {e}", file=sys.stderr)
        return 2
    table = catalogue_table(rows, rays)
    if a.export:
        given = ["OUT" if v == a.out else v for v in (sys.argv[1:] if argv is None else argv)]
        path = export(Path(a.export), rows, out, " ".join(["python -m lab olf-rays"] + given), log=say)
        say(f"wrote {path} ({path.stat().st_size / 1e6:.2f} MB, {len(rows)} lenses)")
    (out / "result.json").write_text(json.dumps({"rays": rays, "seed": a.seed, "lenses": rows}, indent=1,
                                                default=float) + "\n")
    print(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())

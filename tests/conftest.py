import math
import os

import numpy as np
import pytest

# a job that writes a path it did not declare (dcdi_core.outputs) fails here, not silently
os.environ.setdefault("DCDI_CHECK_OUTPUTS", "1")

try:                                     # property-based tests: a few fixed examples by default, many in test-slow
    from hypothesis import settings as _hypothesis_settings
    _hypothesis_settings.register_profile("quick", max_examples=12, deadline=None, derandomize=True,
                                          print_blob=True)
    _hypothesis_settings.register_profile("long", max_examples=300, deadline=None, print_blob=True)
    _hypothesis_settings.load_profile(os.environ.get("DCDI_HYPOTHESIS_PROFILE", "quick"))
except ImportError:                      # the suite's property tests then fail to import, saying so
    pass

from dcdi_core.dataset.rgbd import RGBDFrame, RGBDSource
from dcdi_core.optics.lens import Lens, load_lens

PAPER_LENSES = ["mos-s1", "mos-s2", "double-gauss", "6p"]


def singlet_dict(r1=50.0, r2=math.inf, t=5.0, back=40.0, nd=1.5, sd=10.0, stop_first=True,
                 conic=0.0, asph=None):
    """A singlet in air: optional stop plane 1 mm in front, then the lens."""
    surfs = []
    if stop_first:
        surfs.append({"radius_mm": math.inf, "thickness_mm": 1.0, "material": "air",
                      "semi_diameter_mm": sd * 0.5, "stop": True})
    front = {"radius_mm": r1, "thickness_mm": t, "material": {"nd": nd, "vd": 50.0},
             "semi_diameter_mm": sd, "conic": conic}
    if asph:
        front["aspheric_coefficients"] = asph
    if not stop_first:
        front["stop"] = True
    surfs.append(front)
    surfs.append({"radius_mm": r2, "thickness_mm": back, "material": "air", "semi_diameter_mm": sd})
    return {"schema_version": 1, "id": "test-singlet", "wavelength_nm": 587.5618,
            "sensor": {"semi_diagonal_mm": 5.0}, "surface": surfs}


@pytest.fixture
def singlet():
    return Lens.from_dict(singlet_dict())


@pytest.fixture
def no_ray_olf(monkeypatch):
    """The source rule without the shipped OLF in ray space (``psf.rayfield``):
    for a test of what another store refuses, or of the OLF network."""
    import dcdi_core.psf.sources as sources
    monkeypatch.setattr(sources, "olf_rays_file", lambda: None)


@pytest.fixture(params=PAPER_LENSES)
def paper_lens(request):
    return load_lens(request.param)


def write_rgbd_scene(tmp_path, monkeypatch, height, width, seed=1):
    """The synthetic RGB-D scene as aif.exr and depth.exr in tmp_path, with a
    PSF cache of the test's own: (image, depth)."""
    from dcdi_core.io.images import write_depth, write_image
    from dcdi_core.render.synthetic import synthetic_rgbd
    monkeypatch.setenv("DCDI_CACHE_DIR", str(tmp_path / "cache"))
    img, depth = synthetic_rgbd(height, width, seed=seed)
    write_image(tmp_path / "aif.exr", img)
    write_depth(tmp_path / "depth.exr", depth)
    return img, depth


# ------------------------------------------------- training: kills and DA2T pairs
class Killed(Exception):
    """What ``kill_at`` raises: a run stopped as a kill would stop it."""


def kill_at(n: int):
    """An ``on_step`` callback that stops a training run after step ``n``
    (after any checkpoint due at it), as a kill at that moment would."""
    def on_step(step):
        if step == n:
            raise Killed
    return on_step


# tiny PSF libraries for DA2T pairs: every pair builds in about a second
# refocus=False: the pairs the two-process training test's allowance was set on (4 steps: 99.9 % of the
# weights within 1e-6 of one process's); on pairs of refocused lenses 9 % of them differed by more (up to
# 0.4 of a step), not yet understood
PAIR_FAST = dict(pupil_samples=8, n_wavelengths=3, n_fields=6, n_depths=3, refocus=False)
DACN_ARCH = dict(channels=8, groups=1, blocks=2, window=4)


class Frames(RGBDSource):
    """Six 48 x 64 frames of six scenes: blocks of colour, two depths (0.9 and 5 m)."""

    def __init__(self):
        self.f = {}
        for k in range(6):
            rng = np.random.default_rng(k)
            img = np.kron(rng.uniform(0.1, 0.9, (12, 16, 3)), np.ones((4, 4, 1))).astype(np.float32)
            dep = np.where(np.arange(64)[None, :] < 20 + 4 * k, 0.9, 5.0) * np.ones((48, 1))
            self.f[f"scene{k}"] = RGBDFrame(f"scene{k}", f"scene{k}", img, dep.astype(np.float32), "test")

    def ids(self):
        return sorted(self.f)

    def load(self, id):
        return self.f[id]


@pytest.fixture(scope="module")
def pairs(tmp_path_factory):
    """DA2T pairs of ``Frames`` for mos-s2 (one set a test module)."""
    from dcdi_core.models.dacn.data import DA2TConfig, build_pairs
    root = tmp_path_factory.mktemp("pairs")
    build_pairs(Frames(), root, DA2TConfig(lens="mos-s2", **PAIR_FAST))
    return root


def dacn_config(data, **kw):
    """A tiny DACN training config on the pairs at ``data`` (6 iterations,
    checkpoints at 3 and 6; the six scenes split 3 / 1 / 2)."""
    from dcdi_core.models.dacn.config import DACNTrainConfig
    base = dict(data=str(data), config="tiny", arch=DACN_ARCH, iters=6, batch=2, crop=16, lr=1e-3, val_size=32,
                checkpoint_every=3, val_fraction=1 / 6, test_fraction=2 / 6, threads=1)
    base.update(kw)
    return DACNTrainConfig(**base)

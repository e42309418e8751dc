import math

import pytest

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

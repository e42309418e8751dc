"""The lens catalogue's figures: each lens beside its source's stated focal
length and f-number, as lenses/README.md lists them.

For every lens in lenses/ that is not one of the paper's four: the
paraxial EFL and F-number at the design wavelength and their difference
from the stated ones, the real working F-number, the diagonal field of
view and the distortion at the sensor's corner (``optics.report``, what
`dcdi lens info` prints), and the fraction of the rays the clear apertures
vignette at the corner (field 1, object at infinity, green).

Run ``python -m lab catalogue-table`` (a few seconds).
"""
from __future__ import annotations

PAPER_LENSES = ("mos-s1", "mos-s2", "double-gauss", "6p")


def rows() -> list[dict]:
    import warnings

    from dcdi_core.optics.lens import available_lenses, load_lens
    from dcdi_core.optics.report import lens_info
    from dcdi_core.psf.compute import KernelTooSmallWarning, PSFSettings, psf
    out = []
    for lens_id in sorted(set(available_lenses()) - set(PAPER_LENSES)):
        lens = load_lens(lens_id)
        info = lens_info(lens)
        settings = PSFSettings(kernel_size=21, pupil_samples=48, n_wavelengths=1, wavelength_nm=550.0,
                               pixel_pitch_mm=0.05)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", KernelTooSmallWarning)
            vig = float(psf(lens, depth_m=float("inf"), field=1.0, settings=settings).vignetted_fraction[1])
        out.append({"id": lens_id, "name": lens.name, "stated": lens.stated, "info": info, "vignetted": vig})
    return out


def format_table(rows_: list[dict]) -> str:
    out = ["| lens | name | stated EFL mm, F/# | traced EFL mm (diff) | paraxial F/# (diff) | working F/# | "
           "diagonal FoV deg | distortion at the corner | vignetted at the corner |",
           "|---|---|---|---|---|---|---|---|---|"]
    for r in rows_:
        i, st = r["info"], r["stated"]
        efl, fn = i["effective_focal_length_mm"], i["f_number"]
        out.append(f"| `{r['id']}` | {r['name']} | {st['effective_focal_length_mm']:g}, {st['f_number']:g} | "
                   f"{efl:.2f} ({100 * (efl / st['effective_focal_length_mm'] - 1):+.2f} %) | "
                   f"{fn:.3f} ({100 * (fn / st['f_number'] - 1):+.1f} %) | {i['working_f_number']:.2f} | "
                   f"{i['field_of_view_deg']:.1f} | {100 * i['distortion_at_field_1']:+.2f} % | "
                   f"{100 * r['vignetted']:.0f} % |")
    return "\n".join(out)


def main(argv=None) -> int:
    import argparse
    argparse.ArgumentParser(prog="python -m lab catalogue-table",
                            description="the lens catalogue's figures (module docstring)").parse_args(argv)
    print(format_table(rows()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

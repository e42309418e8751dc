"""The pixel pitch has one home: one option in every verb that takes it,
one rule for its default said alike in each help, and one field in a
render request (a PSF settings' pitch moves there)."""
from __future__ import annotations

import pytest

from dcdi_core.cli import build_parser
from dcdi_core.cli.common import PIXEL_PITCH_RULE
from dcdi_core.errors import InputRangeError
from dcdi_core.optics.lens import load_lens
from dcdi_core.psf.compute import PSFSettings
from dcdi_core.render.request import RenderRequest


def _verbs(parser, prefix=()):
    """(command words, parser) of every leaf verb."""
    import argparse
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        yield prefix, parser
        return
    for name, sub in subs[0].choices.items():
        yield from _verbs(sub, prefix + (name,))


def test_every_verb_has_one_pixel_pitch_option_with_the_one_rule():
    seen = []
    for words, parser in _verbs(build_parser()):
        options = [a for a in parser._actions if "--pixel-pitch" in a.option_strings
                   or "--image-pixel-pitch" in a.option_strings]
        if not options:
            continue
        assert len(options) == 1, (words, [a.option_strings for a in options])
        assert options[0].help == PIXEL_PITCH_RULE, words
        seen.append(" ".join(words))
    for verb in ("simulate", "bokeh", "dof", "correct", "depth estimate", "psf"):
        assert verb in seen, (verb, seen)


def test_the_old_spelling_is_the_same_option():
    p = build_parser()
    a = p.parse_args(["bokeh", "--image", "a.exr", "--depth", "d.exr", "--lens", "6p", "-o", "o.exr",
                      "--image-pixel-pitch", "0.01"])
    b = p.parse_args(["bokeh", "--image", "a.exr", "--depth", "d.exr", "--lens", "6p", "-o", "o.exr",
                      "--pixel-pitch", "0.01"])
    assert a.image_pixel_pitch == b.image_pixel_pitch == 0.01


def test_a_render_request_holds_the_pitch_in_one_field():
    lens = load_lens("6p")
    r = RenderRequest(lens, psf=PSFSettings(pixel_pitch_mm=0.01))
    assert r.image_pixel_pitch_mm == 0.01 and r.psf.pixel_pitch_mm is None and r.settings.pixel_pitch_mm is None
    assert RenderRequest(lens, psf=PSFSettings(pixel_pitch_mm=0.01), image_pixel_pitch_mm=0.01).psf == r.psf
    with pytest.raises(InputRangeError, match="leave one out"):
        RenderRequest(lens, psf=PSFSettings(pixel_pitch_mm=0.01), image_pixel_pitch_mm=0.02)
    # a pitch no kernel can hold is refused naming what was given
    with pytest.raises(InputRangeError, match="pixel_pitch_mm"):
        RenderRequest(lens, psf=PSFSettings(pixel_pitch_mm=1e-9))

"""The source rule: which PSFs serve a job that names no source.

``psf.sources.psf_source`` tries the stores in ``RULE_ORDER`` and traces
where none serves the request; every text that states the rule (the
command line's help, docs/psf.md) is made from here (:func:`rule_text`).
Kept apart from ``psf.sources`` so that a parser can say it without
importing the engine.
"""
from __future__ import annotations

from types import MappingProxyType

# the source rule: the stores tried in this order (``psf_source``), tracing when none serves; every text that
# states the rule is made from here (``rule_text``)
RULE_ORDER = ("basis", "raymap", "olf")
RULE_PHRASES = MappingProxyType({
    "basis": "the lens's PSF basis where it covers the lens (its prescription) and the request (pixel pitch, "
             "focus, PSF settings)",
    "raymap": "its ray map where one ships (the catalogue's lenses: any focus, f-number, blades and pitch)",
    "olf": "the Omni-Lens-Field where it covers the request (in ray space for the paper's four lenses: any focus, "
           "f-number, blades and pitch; else its network)",
})


def rule_text() -> str:
    """The source rule in words: which PSFs serve a job that names none."""
    return ", else ".join(RULE_PHRASES[k] for k in RULE_ORDER) + ", else traced"

"""The networks' registry as a test wants it, restored after the test."""
from __future__ import annotations

from dataclasses import replace


def dacn_recorded_better(monkeypatch, lens_ids: tuple) -> dict:
    """NETWORKS as if the DACN study had found the shipped DACNs of
    ``lens_ids`` (only) better than the deconvolution; the registry and the
    pipeline both see it."""
    import dcdi_core.app.correction_rule as pipeline
    from dcdi_core import shipped as registry
    nets = dict(registry.NETWORKS, dacn=replace(registry.NETWORKS["dacn"], beats_deconvolution=tuple(lens_ids)))
    monkeypatch.setattr(registry, "NETWORKS", nets)
    monkeypatch.setattr(pipeline, "NETWORKS", nets)
    return nets

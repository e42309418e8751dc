"""Omni-Lens-Field: one MLP of a lens's PSFs over field, depth and focus.

``spec`` (torch-free sizes and variants), ``arch`` (the network), ``data``
(ray-traced PSF samples and the encodings), ``config`` (the training config),
``train`` (on the shared loop of ``models.common``), ``export`` (to the
.npz that ``psf.olf`` runs in numpy)."""

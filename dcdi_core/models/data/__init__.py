"""Training data: PSF samples for the Omni-Lens-Field (``psf_samples``)."""

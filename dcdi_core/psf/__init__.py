"""Point spread functions: ray-traced RGB PSFs of a lens, their spectral weighting and library."""

"""Rendering: PSF maps, patch-wise convolution (aberrations, bokeh), distortion and sensor noise."""

"""The depth-aware correction network (DACN) and its DA2T training.

``spec`` (torch-free configs), ``layers`` (deformable convolution, channel
cross-attention / RDICAB, Swin and EDSR blocks), ``arch`` (the network),
``data`` (DA2T pairs: the depth-aware degradation of RGB-D frames, pre-built
and cropped), ``config`` and ``train`` (on the shared loop of
``models.common``), ``export`` (to .npz), ``correct`` (tiled inference on an
image of any size), ``evaluate`` (held-out scores per scene and depth band)."""

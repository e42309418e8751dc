"""Training data: PSF samples for the Omni-Lens-Field (``psf_samples``);
for DACN, RGB-D readers (``rgbd``: factory folders, a generic folder,
NYUv2's labeled .mat, Middlebury 2014), the depth encodings (``depth``),
the split by scene (``split``) and the DA2T degradation with pre-built
pairs and training crops (``da2t``)."""

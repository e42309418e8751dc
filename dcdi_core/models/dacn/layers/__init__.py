"""Building blocks of the networks (torch): the modulated deformable 3x3
convolution in plain torch (``deform_conv``), channel cross-attention and
RDICAB (``attention``), Swin transformer blocks (``swin``) and EDSR residual
blocks (``blocks``)."""

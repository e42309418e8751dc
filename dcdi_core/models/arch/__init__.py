"""Network architectures. ``spec`` is torch-free (shapes, sizes, parameter
counts); the modules (``olf``) import torch."""

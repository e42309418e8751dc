"""Training: configs as data (``config``), a plain loop with atomic
checkpoints and exact resume (``loop``); the device and torchrun's
processes (``distributed``)."""

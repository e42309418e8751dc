"""The dataset factory (product, not part of the add-on zip: it needs the
repository's ``scenes/`` and runs under ``blender --background`` or the pip
``bpy``): seeded scenes rendered all-in-focus with metric depth, then the
depth-aware simulation of each lens. ``batch`` is the run; the Blender it
runs in (``blender``), its options (``options``), the settings a folder
records (``settings``), the folder made ready (``folder``), the Cycles
render (``render``), a sample's stages (``samples``) and its commit with its
manifest line (``commit``), the process's timings (``meters``); one data set
from shard folders (``merge_shards``); job-array scripts for Slurm and
Kubernetes (``cluster/``)."""

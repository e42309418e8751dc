"""The dataset factory (product, not part of the add-on zip: it needs the
repository's ``scenes/`` and runs under ``blender --background`` or the pip
``bpy``): seeded scenes rendered all-in-focus with metric depth, then the
depth-aware simulation of each lens (``batch``); one data set from shard
folders (``merge_shards``); job-array scripts for Slurm and Kubernetes
(``cluster/``)."""

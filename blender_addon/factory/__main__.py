"""``python -m blender_addon.factory ...``: the dataset factory (see ``batch``).
Blender is checked once the recipe is known: the numpy recipe and the merge
of shard folders need none."""
import sys

from .batch import run

sys.exit(run())

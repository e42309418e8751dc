"""``python -m blender_addon.factory ...``: the dataset factory (see ``batch``)."""
import sys

from .batch import check_blender, run

if sys.argv[1:2] != ["merge"]:          # the merge of shard folders needs no Blender
    check_blender()
sys.exit(run())

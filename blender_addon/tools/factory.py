"""The old spelling of the dataset factory, kept for one release:
``python -m blender_addon.factory`` (or ``blender --background --python
blender_addon/factory/batch.py -- ...``) is the factory now."""
import runpy
import sys
from pathlib import Path

if __name__ == "__main__":
    print("note: blender_addon.tools.factory is now blender_addon.factory; the old name goes in the next release",
          file=sys.stderr)
    if __package__ in (None, ""):
        sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
    runpy.run_module("blender_addon.factory", run_name="__main__", alter_sys=True)

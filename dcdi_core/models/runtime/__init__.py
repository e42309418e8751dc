"""numpy only: what runs an exported model without torch (the part of
``dcdi_core.models`` that the Blender add-on bundles)."""

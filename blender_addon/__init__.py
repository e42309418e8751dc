"""Blender side of dcdi: the dataset factory (and, later, the lens panel).

bpy only: it gathers pixels and settings from Blender, calls dcdi_core, and
puts pixels back; no optics here.
"""

"""Procedural, seeded scene recipes for the dataset factory (bpy)."""

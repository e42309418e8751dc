"""Data sets on disk, numpy only (no bpy, no torch).

``factory_folder``: the dataset factory's folder format, defined once (file
names, layout, sample ids, the manifest of finished samples, the settings
record): the factory (blender_addon/factory/) writes it with these
helpers and every reader reads it through them.

``textures``: a user's folder of image textures (photographs, CC0 material
sets) that the factory maps onto surfaces.

``rgbd``: readers of all-in-focus RGB-D frames (image and metric depth) for
training: a factory folder, a generic folder (``images/``, ``depth/``),
NYU Depth v2's labeled ``.mat`` and Middlebury 2014's scene folders.
"""

"""Procedural assets: the rendered objects (``objects``), the furnished room around a scene's supports
(``scenes``), their materials, and the physics stand-in meshes (``standin``, ``collision``).

Every module here imports bpy inside the functions that build Blender data only, so the pure geometry
(stand-in meshes, collision hulls, ``objects.object_vertices``, ``scenes.slide_clear``) works without Blender.
"""

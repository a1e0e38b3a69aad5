"""Everything that touches Blender (bpy): session reset, rigid-body simulation, camera, render.

Importing this package imports nothing; ``bpy`` is loaded by the functions that need it
(``session.import_bpy``), so ``rigidbench`` works without Blender until a simulation runs.
"""

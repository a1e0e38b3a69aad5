"""Everything that touches Blender (bpy): session reset, rigid-body simulation, camera, render, and the
procedural objects and furnished scenes (``blender.assets``).

Importing this package imports nothing; ``bpy`` is loaded by the functions that need it
(``session.import_bpy``), so ``rigidbench`` works without Blender until a simulation runs. No module
outside this package imports bpy (tests/contract/test_import_graph.py checks it).
"""

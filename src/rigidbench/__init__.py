"""RigidBench: simulator-grounded evaluation of rigid-body physics in video generation models.

Importing the package is cheap: heavy stages (bpy, torch, av) load only when used.
"""

__version__ = "0.1.0"

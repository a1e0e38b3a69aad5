"""RigidBench: simulator-grounded evaluation of rigid-body physics in video generation models.

Importing the package is cheap: heavy stages (bpy, torch, av) load only when used.

    import rigidbench
    for example in rigidbench.Benchmark.load("data/eval"):
        example.id, example.image, example.prompt, example.negative_prompt
"""

# benchmark.py needs the standard library only, so importing it here keeps `import rigidbench` cheap.
from .benchmark import Benchmark, Example

__version__ = "0.1.0"

__all__ = ["Benchmark", "Example", "__version__"]

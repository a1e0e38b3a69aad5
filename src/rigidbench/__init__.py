"""RigidBench: simulator-grounded evaluation of rigid-body physics in video generation models.

Importing the package is cheap: heavy stages (bpy, torch, av) load only when used.

    import rigidbench
    for example in rigidbench.Benchmark.load("data/eval"):
        example.id, example.image, example.prompt, example.negative_prompt
"""

__version__ = "0.1.0"


def __getattr__(name: str):
    if name in ("Benchmark", "Example"):
        from . import benchmark

        return getattr(benchmark, name)
    raise AttributeError(f"module 'rigidbench' has no attribute '{name}'")

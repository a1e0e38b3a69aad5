"""RigidBench: simulator-grounded evaluation of rigid-body physics in video generation models.

Importing the package is cheap: heavy stages (bpy, torch, av) load only when used.

    import rigidbench
    for example in rigidbench.Benchmark.load("data/eval"):
        example.id, example.image, example.prompt, example.negative_prompt
    first = rigidbench.Benchmark.load("data")[0]  # by position; ["00007"] by id
    rigidbench.write_inputs("data")  # data/inputs.jsonl (export_inputs_jsonl: the release's name)
"""

# benchmark.py needs the standard library only, so importing it here keeps `import rigidbench` cheap.
from .benchmark import Benchmark, BenchmarkExample, Example, export_inputs_jsonl, write_inputs

__version__ = "0.1.0"

__all__ = ["Benchmark", "BenchmarkExample", "Example", "export_inputs_jsonl", "write_inputs", "__version__"]

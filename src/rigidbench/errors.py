"""Every error RigidBench raises on purpose, under one base class.

A ``RigidBenchError`` means "this input (a file, an example, an option) cannot be used, and the
message says which and what to do". Per-example loops record it (and I/O errors) as "example
failed" and go on with the other examples; anything else is a bug and stops the run with a
traceback. The command line prints a ``RigidBenchError`` as one line and exits with status 2.

One exception: ``MissingExtra`` (an optional package that is not installed) is a ModuleNotFoundError, so that it
stops the run instead of failing each example; the command line prints it as one line too.

This module imports nothing, so every layer can raise these errors without importing upward.
"""

from __future__ import annotations


class RigidBenchError(Exception):
    """Base of every error of ours; the message names the file or example and what to do next."""


class UserError(RigidBenchError):
    """A command-line input that cannot be used (an unknown name, a wrong directory, a bad value)."""


class UnknownNameError(UserError, KeyError):
    """A name that is not in a registry; the message lists the nearest known names."""

    def __str__(self) -> str:  # KeyError would quote the message
        return str(self.args[0]) if self.args else ""


class ConfigError(RigidBenchError, ValueError):
    """A configuration file that cannot be used; the message names the file and the field."""


class SpecError(RigidBenchError, ValueError):
    """A manifest row from which no scene can be built (e.g. no room for the objects)."""


class BundleError(RigidBenchError, ValueError):
    """A sample bundle that is missing, incomplete or inconsistent."""


class VideoError(RigidBenchError):
    """A video file that is missing, undecodable or empty; names the file and the reason."""

    def __init__(self, path, reason: str):
        from pathlib import Path  # (stdlib; this module imports nothing at its top)

        self.path = Path(path)
        self.reason = reason
        super().__init__(f"{path}: {reason}")


class PerceptionError(RigidBenchError):
    """Perception could not run for an example; names the example and what to do."""


class WeightsUnavailable(RigidBenchError, OSError):
    """Model weights are not available locally; the message says where we looked and how to fetch them."""


class PredictionError(RigidBenchError):
    """A predictor could not produce a video for an example (e.g. a counterfactual re-render failed)."""


class EvaluationError(RigidBenchError):
    """An example could not be evaluated; the message names it and the reason."""


class ReportError(RigidBenchError):
    """Evaluation runs that cannot be put into one report."""


class MissingExtra(ModuleNotFoundError):
    """An optional package is not installed; the message names the extra that installs it (``rigidbench.extras``).

    Not a ``RigidBenchError`` on purpose: a missing package is no fault of one example, so the per-example loops
    (which catch ``EXAMPLE_ERRORS``) let it through, and the command line prints it as one line (status 2)."""


#: what a per-example loop records as "this example failed" instead of stopping the run
EXAMPLE_ERRORS: tuple[type[BaseException], ...] = (RigidBenchError, OSError)

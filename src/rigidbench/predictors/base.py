"""The ``Predictor`` interface: everything that turns a reference example's first frame and prompt
into a video.

A predictor is registered once in ``predictors.PREDICTORS`` with a ``PredictorInfo``: its name,
a one-line description, its kind (failure mode, local model, hosted model, user plug-in), whether
it needs Blender and whether it writes the exact world state its video shows (which ``--perception
gt`` then scores). ``PredictorInfo.create()`` imports its target and returns a ``Predictor`` whose
``predict(sample, ctx)`` gives a ``Prediction``; the predict stage writes it to disk.

The target may be a ``Predictor`` subclass (constructed with the info), a failure-mode function
``f(sample, severity, **options) -> Prediction``, or, for a plug-in, a function
``f(sample, ctx) -> Prediction``.

A video model reads its inputs from the sample exactly as the paper gives them to every model:
``model_inputs(sample)`` returns the first frame, the task prompt followed by the paper's fixed
suffix, and the paper's negative prompt.

Seeds: ``--seed`` is a base seed. The predict stage gives each example its own seed,
``example_seed(base, example id)`` (a SHA-256 of both, so it is the same on every machine and in
every Python process), passes it as ``ctx.seed`` and records it per example in generation.json. With several
samples per example (``predict --samples K``) sample k gets ``sample_seed(base, example id, k)``; sample 0's is
the example's seed, so one sample per example is seeded as before.
"""

from __future__ import annotations

import enum
import hashlib
import inspect
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any, Callable, ClassVar, Mapping

import numpy as np

from ..benchmark import NEGATIVE_PROMPT, full_prompt
from ..context import RunContext
from ..errors import UserError
from ..folders import SCRATCH_DIR, PredictionsFolder  # noqa: F401 (SCRATCH_DIR re-exported)
from ..perception.gt import WorldState
from ..registry import load_target


#: How an example's seed follows from the base seed (recorded in every run's settings and generation.json).
SEED_RULE = ("per example: the first 4 bytes of sha256('<base seed>/<example id>') (UTF-8) as a big-endian integer, "
             "top bit cleared (0 <= seed < 2**31)")


def example_seed(base_seed: int, example_id: str) -> int:
    """The seed of example ``example_id`` in a run with base seed ``base_seed``: an int in [0, 2**31), the same
    on every machine and Python process (a SHA-256, not ``hash()``); different examples get unrelated seeds."""
    digest = hashlib.sha256(f"{int(base_seed)}/{example_id}".encode("utf-8")).digest()
    return int.from_bytes(digest[:4], "big") & 0x7FFF_FFFF


#: How sample k of an example follows (``predict --samples K``); sample 0's seed is the example's, so K = 1 is today's run.
SAMPLE_SEED_RULE = ("sample 0: the example's seed; sample k >= 1: the seed of example '<example id>.s<k>' by the "
                    "same rule")


def sample_seed(base_seed: int, example_id: str, k: int) -> int:
    """The seed of sample ``k`` of example ``example_id`` (``SAMPLE_SEED_RULE``): ``example_seed(base, id)`` for
    k = 0, so one sample per example is seeded exactly as before; ``example_seed(base, '<id>.s<k>')`` for k >= 1
    (the sample's item name, ``folders.sample_item``)."""
    k = int(k)
    if k < 0:
        raise ValueError(f"sample index must be >= 0, got {k}")
    return example_seed(base_seed, example_id if k == 0 else f"{example_id}.s{k}")


class Kind(str, enum.Enum):
    FAILURE_MODE = "failure mode"
    LOCAL = "local model"
    HOSTED = "hosted model"
    PLUGIN = "user plug-in"


@dataclass
class Prediction:
    """What a predictor made for one example: frames (T,H,W,3) uint8 at times_s (T,) seconds, or
    ``video_path``, a video file already encoded (e.g. a hosted model's download), kept as it is.

    state: the exact world state the video shows, when known (failure modes); lossless: encode the
    frames losslessly (failure modes, so gt perception sees exactly the frames, and the local video models,
    so scoring sees exactly what they generated) or as H.264 4:2:0 crf 18;
    metadata: per-example facts for generation.json (prediction id, seed, timings, cost)."""

    frames: np.ndarray | None = None
    times_s: np.ndarray | None = None
    state: WorldState | None = None
    video_path: Path | None = None
    lossless: bool = True
    metadata: dict[str, Any] = field(default_factory=dict)

    @property
    def fps(self) -> float:
        """Frame rate implied by the timestamps (the median frame interval)."""
        if self.times_s is None or len(self.times_s) < 2:
            raise ValueError("a prediction needs at least two timestamped frames to have a frame rate")
        return float(1.0 / np.median(np.diff(self.times_s)))


@dataclass(frozen=True)
class PredictContext:
    """What a predictor may use besides the example: the run context (configuration registry, device,
    cache), the failure-mode severity in [0, 1], the generation seed (the predict stage passes each example
    its own, ``example_seed(--seed, example id)``; it is the base seed in settings), for predictors that render a
    directory in which to keep their bundle (None: a temporary one), the output directory of the run
    (where a predictor may keep per-example state such as a hosted prediction id), model options
    from the command line (e.g. offload, checkpoint, concurrency; ``predictors.options.model_options``
    makes them: JSON values, only those given), which a predictor reads typed with ``Predictor.options``,
    and ``item``: the name of the prediction being made, ``<id>`` or ``<id>.s<k>`` for sample k of several
    (``folders.sample_item``; None: the example's own id). A predictor that keeps state of its own per
    prediction (a hosted model's paid prediction id) keys it by ``item_of(sample)``, so two samples of one
    example never share it."""

    run: RunContext = field(default_factory=RunContext)
    severity: float = 1.0
    seed: int = 0
    keep_bundle_dir: Path | None = None
    out_dir: Path | None = None
    options: Mapping[str, Any] = field(default_factory=lambda: MappingProxyType({}))
    item: str | None = None

    @property
    def registry(self):
        return self.run.registry

    def item_of(self, sample) -> str:
        """The name of the prediction of ``sample`` being made: ``item``, else the example's id (its folder)."""
        return self.item or Path(sample.path).name

    def option(self, name: str, default: Any = None) -> Any:
        """A model option, or ``default`` when it was not given (None counts as not given)."""
        value = self.options.get(name)
        return default if value is None else value


@dataclass(frozen=True)
class ModelInputs:
    """What every video model is given (paper, appendix B.1): the first frame (H,W,3) uint8 and its PNG,
    the task prompt followed by the fixed suffix, and the negative prompt (for models that take one)."""

    image: np.ndarray
    image_path: Path
    prompt: str
    negative_prompt: str


def model_inputs(sample) -> ModelInputs:
    """The model inputs of a reference ``Sample``."""
    return ModelInputs(sample.frame(0), sample.first_frame_path, full_prompt(sample.prompt), NEGATIVE_PROMPT)


@dataclass(frozen=True)
class PredictorInfo:
    """Registry entry of a predictor. ``target`` is "module:attr"; see the module docstring. ``options``:
    the dataclass of its options (``predictors.options``; the same as its class's ``options_type``), None
    when it takes none, so they are known from the name alone (nothing imported, no weights loaded)."""

    name: str
    target: str
    description: str
    kind: Kind
    needs_blender: bool = False
    writes_state: bool = False
    aliases: tuple[str, ...] = ()
    options: type | None = None

    def create(self) -> "Predictor":
        """Import the target and return a ready ``Predictor``."""
        obj = load_target(self.target, f"predictor '{self.name}'")
        if isinstance(obj, type) and issubclass(obj, Predictor):
            return obj(self)
        if not callable(obj):
            raise UserError(f"predictor '{self.name}': {self.target} is neither a Predictor class nor a function; "
                            "name one, e.g. mypackage.module:MyModel (a Predictor subclass or a function "
                            "f(sample, ctx) -> Prediction)")
        if self.kind == Kind.FAILURE_MODE:
            return FailureMode(self, obj)
        return FunctionPredictor(self, obj)


class Predictor(ABC):
    """One video model (or failure mode); ``info`` is its registry entry.

    ``paid``: each prediction (each sample of each example) is a paid call to a hosted API (``--dry-run`` and
    ``audit`` count them);
    ``concurrency(ctx)``: how many examples the predict stage may run at once in threads;
    ``options_type``: the dataclass of its options (a ``predictors.options.ModelOptions``; None: none), which
    ``options(ctx)`` reads from ``ctx.options``."""

    paid: bool = False
    options_type: ClassVar[type | None] = None

    def __init__(self, info: PredictorInfo):
        self.info = info

    @property
    def name(self) -> str:
        return self.info.name

    def options(self, ctx: PredictContext):
        """This predictor's options in ``ctx.options``, typed and checked (an instance of ``options_type``;
        options of other models are ignored; a bad value is a UserError naming the option); None when it
        takes none."""
        if self.options_type is None:
            return None
        return self.options_type.from_mapping(ctx.options, model=self.name)

    @abstractmethod
    def predict(self, sample, ctx: PredictContext) -> Prediction:
        """The video this predictor makes for reference ``sample`` (a ``groundtruth.bundle.Sample``)."""

    def settings(self, ctx: PredictContext) -> dict[str, Any]:
        """What, besides the predictor's name, makes its outputs differ (recorded; a change means a rerun)."""
        return {"seed": ctx.seed}

    def generation_info(self, ctx: PredictContext) -> dict[str, Any]:
        """Model identifier, revision and every generation parameter, for generation.json."""
        return {}

    def describe(self, sample, ctx: PredictContext) -> dict[str, Any]:
        """The request this predictor would make for ``sample`` (``--dry-run``; no secrets, images elided)."""
        inputs = model_inputs(sample)
        return {"image": str(inputs.image_path), "prompt": inputs.prompt, "negative_prompt": inputs.negative_prompt,
                "seed": ctx.seed}

    def concurrency(self, ctx: PredictContext) -> int:
        return 1

    def preflight(self, ctx: PredictContext) -> None:
        """Checked once before any example runs, and only when one will (e.g. a hosted model's token): raise a
        UserError saying what to fix. Nothing by default."""

    def recover_record(self, out_dir: Path, sample_id: str) -> dict | None:
        """What this predictor's own files in ``out_dir`` say about ``sample_id``'s finished prediction (e.g. a
        hosted prediction's id), for a video whose record was lost; None (the default) when nothing."""
        return None

    def request_stop(self) -> None:
        """The run is stopping (SIGTERM, Ctrl-C): start nothing new. Nothing by default."""

    def close(self) -> None:
        """Release models or connections (called once after the last example)."""


class FailureMode(Predictor):
    """A failure mode ``f(sample, severity, **options)``; options it accepts among ``registry`` (the
    configuration it re-simulates with), ``bundle_dir`` (where to keep its re-rendered bundle) and
    ``scratch_dir`` (where to put its temporary files: ``OUT/.scratch`` of the run, None for $TMPDIR)."""

    def __init__(self, info: PredictorInfo, function: Callable):
        super().__init__(info)
        self.function = function
        self._accepts = set(inspect.signature(function).parameters)

    def predict(self, sample, ctx: PredictContext) -> Prediction:
        options = {"registry": ctx.registry, "bundle_dir": ctx.keep_bundle_dir,
                   "scratch_dir": PredictionsFolder(ctx.out_dir).scratch_dir if ctx.out_dir is not None else None}
        if "seed" in self._accepts and ctx.item not in (None, getattr(sample, "sample_id", None)):
            # sample k >= 1 of a random failure mode (one taking a ``seed``, e.g. camera-shake): its own draw, from
            # the sample's seed; sample 0 keeps the mode's fixed draw, so one sample per example is as before
            options["seed"] = int(ctx.seed)
        return self.function(sample, float(ctx.severity), **{k: v for k, v in options.items() if k in self._accepts})

    def settings(self, ctx: PredictContext) -> dict[str, Any]:
        return {"severity": float(ctx.severity)}

    def describe(self, sample, ctx: PredictContext) -> dict[str, Any]:
        return {"severity": float(ctx.severity), "re-rendered": self.info.needs_blender}


class FunctionPredictor(Predictor):
    """A plug-in function ``f(sample, ctx) -> Prediction``."""

    def __init__(self, info: PredictorInfo, function: Callable):
        super().__init__(info)
        self.function = function

    def predict(self, sample, ctx: PredictContext) -> Prediction:
        return self.function(sample, ctx)

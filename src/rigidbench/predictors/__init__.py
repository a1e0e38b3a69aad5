"""Everything that makes a video from a reference example, behind one ``Predictor`` interface and
one registry, ``PREDICTORS`` (``rigidbench predict --list`` prints it).

Adding a predictor is one module plus one ``PREDICTORS.add(PredictorInfo(...))`` line here (its options,
if any: a dataclass in ``options``, named by the entry and by the class's ``options_type``); a
user's own model needs no registration at all: ``rigidbench predict mypackage.module:MyModel``
loads any ``Predictor`` subclass or ``f(sample, ctx) -> Prediction`` function by its path.
"""

from __future__ import annotations

from ..errors import UserError
from ..registry import LazyRegistry
from .base import (SEED_RULE, FailureMode, FunctionPredictor, Kind, ModelInputs, PredictContext, Prediction, Predictor,
                   PredictorInfo, SAMPLE_SEED_RULE, example_seed, model_inputs, sample_seed)
from .options import (CosmosOptions, HostedOptions, ModelOptions, TwinOptions, WanOptions, audit_options,
                      format_options, legacy_flags, model_options, options_type, parse_model_args, resolve_options)

PREDICTORS: LazyRegistry[PredictorInfo] = LazyRegistry("predictor")


def _failure_mode(name: str, target: str, description: str, needs_blender: bool = False) -> None:
    PREDICTORS.add(PredictorInfo(name, f"rigidbench.predictors.{target}", description, Kind.FAILURE_MODE,
                                 needs_blender=needs_blender, writes_state=True))


# The failure-mode suite: the reference with one known thing changed by a severity s in [0, 1].
_failure_mode("reference", "image_space:reference", "the reference itself, losslessly re-encoded")
_failure_mode("static", "image_space:static", "motion frozen: time runs at (1 - s) of real time")
_failure_mode("slow", "image_space:slow", "playback (1 + s) times slower")
_failure_mode("fast", "image_space:fast", "playback (1 + s) times faster; the clip ends early")
_failure_mode("delayed", "image_space:delayed", "motion starts 0.5 s x s late")
_failure_mode("gamma", "image_space:gamma", "appearance change: gamma 1 + 1.5 s")
_failure_mode("camera-shake", "image_space:camera_shake", "coherent random per-frame camera shake")
_failure_mode("camera-drift", "image_space:camera_drift", "coherent steady camera pan")
_failure_mode("background-wobble", "image_space:background_wobble", "smooth non-rigid background displacement")
_failure_mode("identity-swap", "identity_swap:identity_swap", "actors re-rendered in another object's materials",
              needs_blender=True)
_failure_mode("gravity", "counterfactuals:gravity", "re-simulated with gravity g (1 + s)", needs_blender=True)
_failure_mode("restitution", "counterfactuals:restitution", "re-simulated with bouncier surfaces, e + s (1 - e)",
              needs_blender=True)
_failure_mode("friction", "counterfactuals:friction", "re-simulated with friction mu (1 - s)", needs_blender=True)
_failure_mode("mass", "counterfactuals:mass", "re-simulated with actor masses alternately x and / (1 + 4 s)",
              needs_blender=True)
_failure_mode("depth-offset", "counterfactuals:depth_offset", "actors re-rendered 0.5 s m nearer the camera",
              needs_blender=True)
# The physical envelope: the reference re-simulated with its initial state and materials drawn within what one
# frame cannot resolve (configs/envelope.yaml); one twin per sample, seeded by the sample's seed.
PREDICTORS.add(PredictorInfo("twin", "rigidbench.predictors.twins:TwinPredictor",
                             "physical twin: initial state and materials perturbed within the envelope x scale "
                             "(default: the severity)", Kind.FAILURE_MODE, needs_blender=True, writes_state=True,
                             options=TwinOptions))

# Video models run locally through diffusers (paper, appendix B.1); their options: predictors/options.py.
PREDICTORS.add(PredictorInfo("wan-2.2", "rigidbench.predictors.wan:WanPredictor",
                             "Wan 2.2 TI2V-5B (diffusers), 1280x704, 49 frames at 24 fps, 50 steps, bf16", Kind.LOCAL,
                             aliases=("wan",), options=WanOptions))
PREDICTORS.add(PredictorInfo("cosmos-2.5", "rigidbench.predictors.cosmos:CosmosPredictor",
                             "Cosmos Predict 2.5-2B post-trained (diffusers), 1280x704, 33 frames at 16 fps, 50 steps, "
                             "bf16", Kind.LOCAL, aliases=("cosmos",), options=CosmosOptions))


ENTRY_POINT_GROUP = "rigidbench.predictors"


def load_entry_points() -> list[str]:
    """Register the predictors installed packages declare under the ``rigidbench.predictors`` entry-point
    group (name = predictor name, value = "module:Class"); returns the names added. Nothing is imported."""
    from importlib.metadata import entry_points

    added = []
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        if ep.name not in PREDICTORS:
            PREDICTORS.add(PredictorInfo(ep.name, ep.value, f"plug-in from {ep.dist.name if ep.dist else ep.value}",
                                         Kind.PLUGIN))
            added.append(ep.name)
    return added


def _hosted(name: str, description: str) -> None:
    PREDICTORS.add(PredictorInfo(name, "rigidbench.predictors.hosted:HostedPredictor", description, Kind.HOSTED,
                                 options=HostedOptions))


# Hosted video models through Replicate (paid; configs/models.yaml holds each one's inputs).
_hosted("veo-3.1", "Google Veo 3.1 (google/veo-3.1), 4 s 720p 16:9, negative prompt")
_hosted("veo-3.1-fast", "Google Veo 3.1 Fast (google/veo-3.1-fast), 4 s 720p 16:9, negative prompt")
_hosted("kling-3.0", "Kling 3.0 (kwaivgi/kling-v3-video), 3 s pro mode 16:9, negative prompt")
_hosted("seedance-2.0", "ByteDance Seedance 2.0 (bytedance/seedance-2.0), 4 s 720p 16:9")
_hosted("seedance-2.0-fast", "ByteDance Seedance 2.0 Fast (bytedance/seedance-2.0-fast), 4 s 720p 16:9")
_hosted("grok-imagine", "xAI Grok Imagine (xai/grok-imagine-video), 4 s 720p, automatic aspect ratio")


def predictor_info(name: str) -> PredictorInfo:
    """The registry entry for ``name`` (entry-point plug-ins included), or an ad-hoc plug-in entry for a
    "package.module:attr" path."""
    if name not in PREDICTORS:
        load_entry_points()
    if name in PREDICTORS:
        return PREDICTORS[name]
    if ":" in name:
        return PredictorInfo(name.rsplit(":", 1)[1], name, f"user plug-in {name}", Kind.PLUGIN)
    raise UserError(PREDICTORS.unknown_message(name)
                    + ". A model of your own: pass its path, e.g. mypackage.module:MyModel")


def failure_modes() -> tuple[str, ...]:
    """Names of the registered failure modes, in registration order."""
    return tuple(n for n, info in PREDICTORS.items() if info.kind == Kind.FAILURE_MODE)


__all__ = ["PREDICTORS", "SEED_RULE", "CosmosOptions", "FailureMode", "FunctionPredictor", "HostedOptions", "Kind",
           "ModelInputs", "ModelOptions", "PredictContext", "Prediction", "Predictor", "PredictorInfo", "TwinOptions",
           "WanOptions",
           "audit_options", "example_seed", "sample_seed", "SAMPLE_SEED_RULE", "failure_modes", "format_options", "legacy_flags", "load_entry_points",
           "model_inputs", "model_options", "options_type", "parse_model_args", "predictor_info", "resolve_options"]

"""Each predictor's typed options: --model-args parsing, typing and checking, the older global flags as
aliases, finding a model's options from its name without importing torch, ``predict --list`` lines, and a
tiny local model receiving its options typed."""

import json
import logging
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType, SimpleNamespace
from typing import Literal

import pytest

from rigidbench.context import RunContext
from rigidbench.errors import UserError
from rigidbench.predictors import (PREDICTORS, CosmosOptions, HostedOptions, Kind, ModelOptions, PredictContext,
                                   Prediction, Predictor, PredictorInfo, WanOptions, audit_options, format_options,
                                   legacy_flags, model_options, options_type, parse_model_args, predictor_info,
                                   resolve_options)
from rigidbench.predictors import local, wan
from rigidbench.predictors.options import LEGACY_FLAGS, LocalOptions, option, option_specs


from fixtures import tiny_video_models as tiny  # noqa: E402

WAN, COSMOS, VEO, STATIC = (PREDICTORS[n] for n in ("wan-2.2", "cosmos-2.5", "veo-3.1", "static"))
WAN_PUBLIC = ("offload, tiled_vae, model_path, revision, height, width, num_frames, steps, guidance_scale, fps, "
              "dtype, checkpoint, sampler, recipe, timestep_dtype, update_dtype, vae_codec")


# -- a plug-in's own options, as a user would declare them ------------------------------------------------------


@dataclass(frozen=True)
class ToyOptions(ModelOptions):
    strength: float = option(0.5, "how strong", minimum=0)
    mode: Literal["a", "b"] = option("a", "which mode")
    offload: bool = option(False, "also takes the older flag")


class ToyModel(Predictor):
    options_type = ToyOptions

    def predict(self, sample, ctx):
        return Prediction(metadata={"options": self.options(ctx)})


class PlainModel(Predictor):  # declares no options

    def predict(self, sample, ctx):
        return Prediction()


# -- parse_model_args -------------------------------------------------------------------------------------------


def test_model_args_are_key_value_pairs_and_a_value_may_hold_equals_signs():
    assert parse_model_args("offload=true,checkpoint=/runs/lr=1e-4/step=500.safetensors") == {
        "offload": "true", "checkpoint": "/runs/lr=1e-4/step=500.safetensors"}
    assert parse_model_args("  offload = true ,  sampler=unipc  ") == {"offload": "true", "sampler": "unipc"}
    assert parse_model_args("revision=") == {"revision": ""}  # an empty value is a value (the type then decides)
    assert parse_model_args(None) == {} and parse_model_args("") == {} and parse_model_args("   ") == {}


@pytest.mark.parametrize("text, named", [
    ("offload=true,,sampler=unipc", "item 2 is empty"),
    ("offload=true,", "item 2 is empty"),
    ("offload=true, tiled_vae", "item 'tiled_vae' is not key=value"),
    ("=true", "item '=true' is not key=value"),
    ("offload=true,offload=false", "option 'offload' is given twice"),
])
def test_bad_model_args_items_are_named(text, named):
    with pytest.raises(UserError, match=named):
        parse_model_args(text)


# -- typing -----------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("text, value", [(t, True) for t in ("true", "1", "yes", "on", "TRUE", " On ")]
                         + [(t, False) for t in ("false", "0", "no", "off", "False")])
def test_booleans_read_every_spelling(text, value):
    opts = resolve_options(WAN, {"offload": text, "tiled_vae": text})
    assert opts.offload is value and opts.tiled_vae is value


def test_every_kind_of_option_is_typed():
    opts = resolve_options(WAN, parse_model_args(
        "offload=yes,model_path=~/models/wan=2.2,revision=abc123,height=352,width=640,num_frames=9,steps=4,"
        "guidance_scale=3.5,fps=12,dtype=float32,checkpoint=ckpt/lr=1e-4,sampler=unipc"))
    assert isinstance(opts, WanOptions)
    assert opts.offload is True and opts.tiled_vae is False  # left out: the default
    assert opts.model_path == Path("~/models/wan=2.2") and isinstance(opts.model_path, Path)
    assert opts.checkpoint == Path("ckpt/lr=1e-4") and opts.revision == "abc123"
    assert (opts.height, opts.width, opts.num_frames, opts.steps) == (352, 640, 9, 4)
    assert all(type(v) is int for v in (opts.height, opts.width, opts.num_frames, opts.steps))
    assert opts.guidance_scale == 3.5 and type(opts.fps) is float and opts.fps == 12.0
    assert opts.dtype == "float32" and opts.sampler == "unipc"
    hosted = resolve_options(VEO, {"concurrency": " 3 ", "repay_expired": "on"})
    assert hosted == HostedOptions(concurrency=3, repay_expired=True) and type(hosted.concurrency) is int
    assert resolve_options(COSMOS, {"no_guardrail": "1"}).no_guardrail is True
    assert resolve_options(VEO, {}) == HostedOptions() and HostedOptions().concurrency == 8


@pytest.mark.parametrize("model, raw, message", [
    (WAN, {"offload": "maybe"}, "wan-2.2: option offload must be true or false .*got 'maybe'"),
    (WAN, {"offload": 2}, "option offload must be true or false"),
    (WAN, {"height": "tall"}, "wan-2.2: option height must be a number \\(an integer\\), got 'tall'"),
    (WAN, {"steps": "2.5"}, "option steps must be a number"),
    (WAN, {"steps": 2.5}, "option steps must be a number"),
    (WAN, {"steps": True}, "option steps must be a number"),
    (WAN, {"num_frames": "0"}, "option num_frames must be at least 1, got 0"),
    (WAN, {"fps": "0"}, "option fps must be positive, got 0.0"),
    (WAN, {"guidance_scale": "strong"}, "option guidance_scale must be a number, got 'strong'"),
    (WAN, {"guidance_scale": "nan"}, "option guidance_scale must be a finite number, got 'nan'"),
    (WAN, {"fps": float("inf")}, "option fps must be a number"),
    (WAN, {"sampler": "ddim"}, "option sampler must be one of flow-euler, unipc, got 'ddim'"),
    (WAN, {"dtype": "int8"}, "option dtype must be one of bfloat16, float16, float32, got 'int8'"),
    (WAN, {"checkpoint": "  "}, "option checkpoint must be a path"),
    (WAN, {"revision": 3}, "option revision must be text"),
    (VEO, {"concurrency": "0"}, "veo-3.1: option concurrency must be at least 1, got 0"),
    (VEO, {"concurrency": "many"}, "option concurrency must be a number \\(an integer\\)"),
])
def test_bad_values_name_the_model_the_option_and_the_value(model, raw, message):
    with pytest.raises(UserError, match=message):
        resolve_options(model, raw)


def test_an_unknown_option_lists_the_models_options():
    with pytest.raises(UserError) as err:
        resolve_options(WAN, {"foo": "1"})
    assert str(err.value) == f"model 'wan-2.2' has no option 'foo'; its options: {WAN_PUBLIC}"
    with pytest.raises(UserError, match="^model 'static' has no option 'offload'; it has no options$"):
        resolve_options(STATIC, {"offload": "true"})
    with pytest.raises(UserError, match="model 'veo-3.1' has no option 'offload'; its options: concurrency, "
                                        "repay_expired$"):
        model_options(VEO, "offload=true")
    with pytest.raises(UserError, match="has no option 'pipeline'"):  # Python-only: not settable from text
        model_options(WAN, "pipeline=x")
    assert resolve_options(STATIC, {}) is None


def test_the_option_choices_are_the_models_own():
    wan_specs = {s.name: s for s in option_specs(WanOptions)}
    assert wan_specs["sampler"].choices == tuple(wan.SAMPLERS) and WanOptions().sampler == wan.DEFAULT_SAMPLER
    assert wan_specs["recipe"].choices == tuple(wan.RECIPES) and WanOptions().recipe == "ours"
    for numerics in wan.RECIPES.values():  # every recipe value is a choice of its option, described in NUMERICS
        assert all(v in wan_specs[k].choices and v in wan.NUMERICS[k] for k, v in numerics.items())
    assert next(s for s in option_specs(LocalOptions) if s.name == "dtype").choices == local.DTYPES
    assert set(LEGACY_FLAGS) <= {s.name for c in (WanOptions, CosmosOptions, HostedOptions) for s in option_specs(c)}


# -- the command line's mapping: --model-args and the older flags ---------------------------------------------


def test_model_options_are_typed_json_values_of_only_what_was_given():
    mapping = model_options(WAN, "offload=true, checkpoint=runs/a=b/lora.safetensors, steps=4")
    assert dict(mapping) == {"offload": True, "checkpoint": "runs/a=b/lora.safetensors", "steps": 4}
    assert json.loads(json.dumps(dict(mapping))) == dict(mapping)  # a worker job carries it as JSON
    with pytest.raises(TypeError):
        mapping["offload"] = False  # read-only
    back = WAN.create().options(PredictContext(options=json.loads(json.dumps(dict(mapping)))))
    assert back == WanOptions(offload=True, checkpoint=Path("runs/a=b/lora.safetensors"), steps=4)
    assert dict(model_options(WAN)) == {} and dict(model_options(STATIC, None, {"offload": True})) == {}


def test_the_older_flags_are_aliases_and_flags_of_other_models_are_ignored():
    args = SimpleNamespace(offload=True, tiled_vae=False, checkpoint=Path("ckpt"), no_guardrail=False,
                           model_path=None, repay_expired=True, sampler="unipc", concurrency=3, severity=1.0)
    legacy = legacy_flags(args)
    assert set(legacy) == set(LEGACY_FLAGS) and "severity" not in legacy
    assert dict(model_options(WAN, None, legacy)) == {"offload": True, "checkpoint": "ckpt", "sampler": "unipc"}
    assert dict(model_options(COSMOS, None, legacy)) == {"offload": True}
    assert dict(model_options(VEO, None, legacy)) == {"concurrency": 3, "repay_expired": True}
    assert dict(model_options(STATIC, None, legacy)) == {}
    assert dict(model_options(VEO, None, legacy_flags(SimpleNamespace()))) == {}  # no such attributes: not given
    # a flag and --model-args together: the same value is fine, different values are an error
    assert dict(model_options(WAN, "offload=yes,tiled_vae=true", legacy))["tiled_vae"] is True
    with pytest.raises(UserError, match="wan-2.2: --offload and --model-args offload=false disagree"):
        model_options(WAN, "offload=false", legacy)
    with pytest.raises(UserError, match="veo-3.1: --concurrency and --model-args concurrency=4 disagree"):
        model_options(VEO, "concurrency=4", legacy)
    assert dict(model_options(VEO, "concurrency=3", legacy))["concurrency"] == 3
    # an older flag's value is checked when it applies to the model, and never when it does not
    with pytest.raises(UserError, match="veo-3.1: --concurrency must be at least 1, got 0"):
        model_options(VEO, None, {"concurrency": 0})
    assert dict(model_options(WAN, None, {"concurrency": 0})) == {}
    # but --model-args keys must be options of the model
    with pytest.raises(UserError, match="model 'wan-2.2' has no option 'concurrency'"):
        model_options(WAN, "concurrency=2")


def test_settings_and_generation_info_are_those_of_the_same_options_given_the_old_way(tmp_path):
    """Today's command line put the flags given into ctx.options as they were (paths as Path objects): the
    typed mapping of the same options records exactly the same settings."""
    (tmp_path / "weights").mkdir()
    old = {"offload": True, "tiled_vae": True, "model_path": tmp_path / "weights", "sampler": "unipc"}
    new = model_options(WAN, None, {**old, "concurrency": 8, "no_guardrail": None, "repay_expired": None})
    assert set(new) == set(old)
    predictor = WAN.create()
    old_ctx, new_ctx = PredictContext(seed=3, options=MappingProxyType(old)), PredictContext(seed=3, options=new)
    assert predictor.settings(new_ctx) == predictor.settings(old_ctx)
    assert predictor.settings(new_ctx)["model"] == str((tmp_path / "weights").resolve())
    assert predictor.generation_info(new_ctx) == predictor.generation_info(old_ctx)
    cosmos = COSMOS.create()
    flags = {"no_guardrail": True}
    assert cosmos.settings(PredictContext(options=model_options(COSMOS, None, flags))) == \
        cosmos.settings(PredictContext(options=MappingProxyType(flags)))
    hosted, given = VEO.create(), {"concurrency": 2, "repay_expired": True}
    ctx = PredictContext(options=model_options(VEO, None, given))
    assert hosted.concurrency(ctx) == 2 and hosted.options(ctx).repay_expired is True
    assert hosted.concurrency(PredictContext()) == 8


def test_a_predictor_reads_its_own_options_and_ignores_others():
    ctx = PredictContext(options=MappingProxyType({"concurrency": "4", "offload": True, "height": None}))
    assert VEO.create().options(ctx) == HostedOptions(concurrency=4)
    assert WAN.create().options(ctx) == WanOptions(offload=True)  # height None: not given
    assert STATIC.create().options(ctx) is None
    with pytest.raises(UserError, match="veo-3.1: option concurrency must be at least 1"):
        VEO.create().concurrency(PredictContext(options=MappingProxyType({"concurrency": 0})))
    assert WanOptions(offload=True, checkpoint=Path("c")).to_mapping() == {"offload": True, "checkpoint": "c"}
    assert WanOptions.from_mapping(WanOptions(sampler="unipc", steps=3).to_mapping()) == WanOptions(sampler="unipc",
                                                                                                    steps=3)


def test_audit_merges_the_options_of_several_models():
    legacy = {"offload": True, "concurrency": 2}
    merged = audit_options([WAN, VEO, STATIC], "tiled_vae=on,repay_expired=yes", legacy)
    assert dict(merged) == {"offload": True, "tiled_vae": True, "concurrency": 2, "repay_expired": True}
    assert WAN.create().options(PredictContext(options=merged)) == WanOptions(offload=True, tiled_vae=True)
    assert VEO.create().options(PredictContext(options=merged)) == HostedOptions(2, True)
    with pytest.raises(UserError, match="none of wan-2.2, veo-3.1 has an option 'foo'; their options: .*concurrency"):
        audit_options([WAN, VEO], "foo=1")
    with pytest.raises(UserError, match="none of static has an option 'offload'; they have no options"):
        audit_options([STATIC], "offload=1")


# -- plug-ins ---------------------------------------------------------------------------------------------------


def test_a_plug_in_declares_its_options_on_its_class():
    info = predictor_info(f"{__name__}:ToyModel")
    assert info.kind == Kind.PLUGIN and options_type(info) is ToyOptions
    mapping = model_options(info, "strength=2,mode=b", {"offload": True, "concurrency": 3})
    assert dict(mapping) == {"strength": 2.0, "mode": "b", "offload": True}
    pred = info.create().predict(None, PredictContext(options=mapping))
    assert pred.metadata["options"] == ToyOptions(2.0, "b", True)
    with pytest.raises(UserError, match="has no option 'steps'; its options: strength, mode, offload"):
        model_options(info, "steps=2")
    assert "strength" in format_options(info) and "how strong" in format_options(info)


def test_a_plug_in_without_options_gets_the_flags_as_before_and_no_model_args():
    info = PredictorInfo("plain", f"{__name__}:PlainModel", "plain", Kind.PLUGIN)
    assert options_type(info) is None and format_options(info) == ""
    assert dict(model_options(info, None, {"offload": True, "checkpoint": Path("c"), "tiled_vae": False})) == {
        "offload": True, "checkpoint": "c"}
    with pytest.raises(UserError, match="model 'plain' has no option 'x'; it has no options .*options_type"):
        model_options(info, "x=1")
    bad = PredictorInfo("bad", f"{__name__}:BadOptionsModel", "bad", Kind.PLUGIN)
    with pytest.raises(UserError, match="options_type must be a dataclass of"):
        options_type(bad)


class BadOptionsModel(PlainModel):
    options_type = dict


# -- the registry and predict --list ----------------------------------------------------------------------------


def test_every_registered_predictor_names_its_options_type_without_importing_torch():
    code = ("import sys; from rigidbench.predictors import PREDICTORS, options_type, format_options, model_options; "
            "found = {n: getattr(options_type(i), '__name__', None) for n, i in PREDICTORS.items()}; "
            "[format_options(i) + str(dict(model_options(i, None, {'offload': True}))) for i in PREDICTORS.values()]; "
            "print(repr(found)); "
            "print(sorted(m for m in ('torch', 'diffusers', 'transformers', 'httpx', 'peft') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.splitlines()
    found = eval(out[0])  # noqa: S307 (our own repr of a dict of names)
    assert out[1] == "[]"
    assert found["wan-2.2"] == "WanOptions" and found["cosmos-2.5"] == "CosmosOptions"
    assert all(found[n] == "HostedOptions" for n, i in PREDICTORS.items() if i.kind == Kind.HOSTED)
    assert all(found[n] is None for n, i in PREDICTORS.items() if i.kind == Kind.FAILURE_MODE and n != "twin")
    assert found["twin"] == "TwinOptions"
    assert set(found) == set(PREDICTORS)


def test_the_registry_entry_and_the_class_name_the_same_options():
    for name, info in PREDICTORS.items():
        assert info.create().options_type is info.options, name


def test_predict_list_shows_each_models_options():
    text = format_options(WAN)
    lines = text.splitlines()
    assert lines[0].split() == ["option", "type", "default", "help"]
    rows = {line.split()[0]: line for line in lines[1:]}
    assert list(rows) == WAN_PUBLIC.split(", ")  # every option but the Python-only pipeline, in order
    assert rows["offload"].split()[1:3] == ["bool", "false"] and rows["offload"].endswith("(also --offload)")
    assert rows["sampler"].split()[1:3] == ["flow-euler|unipc", "flow-euler"]
    assert rows["steps"].split()[1:5] == ["int", ">=", "1", "model's"] and "inference steps" in rows["steps"]
    assert "path" in rows["checkpoint"] and "--checkpoint" in rows["checkpoint"]
    assert "(also --no-guardrail)" in format_options(COSMOS)
    veo = format_options(VEO)
    assert "concurrency" in veo and "int >= 1" in veo and " 8 " in veo and "--repay-expired" in veo
    assert format_options(STATIC) == ""


# -- a tiny local model receives its options typed ---------------------------------------------------------------


@pytest.mark.usefixtures("torch_one_thread")
def test_a_tiny_wan_receives_offload_and_tiled_vae_typed(caplog):
    pytest.importorskip("torch")
    pytest.importorskip("diffusers")
    pytest.importorskip("transformers")
    mapping = model_options(WAN, "offload=true,tiled_vae=on,height=64,width=96,num_frames=5,steps=2")
    assert mapping["offload"] is True and mapping["steps"] == 2
    pipe = tiny.tiny_wan()
    ctx = PredictContext(RunContext(device="cpu"), seed=1, options=MappingProxyType({**mapping, "pipeline": pipe}))
    predictor = WAN.create()
    opts = predictor.options(ctx)
    assert opts.offload is True and opts.tiled_vae is True and opts.pipeline is pipe
    frame = tiny.textured_frame(64, 96)
    sample = SimpleNamespace(frame=lambda i: frame, first_frame_path=Path("frame_0000.png"), prompt="A cube slides.")
    try:
        with caplog.at_level(logging.WARNING, logger="rigidbench.predictors.local"):
            pred = predictor.predict(sample, ctx)
        assert pred.frames.shape == (5, 64, 96, 3)
        assert pipe.vae.use_tiling  # tiled_vae=on reached the pipeline
        assert "offload asks for a GPU" in caplog.text  # offload=true reached it too (on the CPU it says so)
        info = predictor.generation_info(ctx)
        assert info["offload"] is True and info["tiled_vae"] is True and info["num_inference_steps"] == 2
        assert predictor.settings(ctx)["tiled_vae"] is True
    finally:
        predictor.close()

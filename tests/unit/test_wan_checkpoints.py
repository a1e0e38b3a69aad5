"""Loading the authors' release's checkpoint formats (predictors/wan_checkpoints.py) into diffusers'
DiffSynth-named LoRA files (peft lora_A/lora_B with ".default.", kohya lora_down/lora_up + alpha), the
release's Lightning .ckpt, and full state dicts with DiffSynth names (safetensors and .pt); through the
Wan predictor's detect/load functions and probe --backbone too. Expected weights are computed here,
independently of the loader: the DiffSynth names come from this file's own table."""

import sys
import types

import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("diffusers")
pytest.importorskip("safetensors")

from safetensors.torch import save_file  # noqa: E402

from rigidbench.errors import UserError  # noqa: E402
from rigidbench.predictors import wan_checkpoints as load  # noqa: E402

CONFIG = dict(patch_size=(1, 2, 2), num_attention_heads=2, attention_head_dim=8, in_channels=4, out_channels=4,
              text_dim=16, freq_dim=16, ffn_dim=32, num_layers=2, cross_attn_norm=True,
              qk_norm="rms_norm_across_heads", rope_max_seq_len=32)

#: diffusers module -> DiffSynth / original Wan module, written out for this test
TARGETS = {"attn1.to_q": "self_attn.q", "attn1.to_k": "self_attn.k", "attn1.to_v": "self_attn.v",
           "attn1.to_out.0": "self_attn.o", "attn2.to_q": "cross_attn.q", "attn2.to_k": "cross_attn.k",
           "attn2.to_v": "cross_attn.v", "attn2.to_out.0": "cross_attn.o", "ffn.net.0.proj": "ffn.0",
           "ffn.net.2": "ffn.2"}
OTHER = {"attn1.norm_q": "self_attn.norm_q", "attn1.norm_k": "self_attn.norm_k", "attn2.norm_q": "cross_attn.norm_q",
         "attn2.norm_k": "cross_attn.norm_k", "norm2": "norm3"}
TOP = {"condition_embedder.time_embedder.linear_1": "time_embedding.0",
       "condition_embedder.time_embedder.linear_2": "time_embedding.2",
       "condition_embedder.time_proj": "time_projection.1",
       "condition_embedder.text_embedder.linear_1": "text_embedding.0",
       "condition_embedder.text_embedder.linear_2": "text_embedding.2",
       "proj_out": "head.head", "patch_embedding": "patch_embedding"}


def transformer(seed=0):
    from diffusers import WanTransformer3DModel

    torch.manual_seed(seed)
    return WanTransformer3DModel(**CONFIG).eval()


def diffsynth_key(key: str) -> str:
    """A diffusers state-dict key in DiffSynth's names (the inverse of what the loader must do)."""
    if key == "scale_shift_table":
        return "head.modulation"
    if key.startswith("blocks."):
        _, index, rest = key.split(".", 2)
        if rest == "scale_shift_table":
            return f"blocks.{index}.modulation"
        for table in (TARGETS, OTHER):
            for ours, theirs in table.items():
                if rest.startswith(ours + "."):
                    return f"blocks.{index}.{theirs}{rest[len(ours):]}"
        raise AssertionError(f"no DiffSynth name for {key}")
    for ours, theirs in TOP.items():
        if key.startswith(ours + "."):
            return theirs + key[len(ours):]
    raise AssertionError(f"no DiffSynth name for {key}")


def random_lora(model, rank, seed=1):
    """{diffusers module: (A (r, in), B (out, r))} for every attention and FFN projection of every block."""
    g = torch.Generator().manual_seed(seed)
    out = {}
    for i, _ in enumerate(model.blocks):
        for name in TARGETS:
            w = model.get_submodule(f"blocks.{i}.{name}").weight
            out[f"blocks.{i}.{name}"] = (torch.randn(rank, w.shape[1], generator=g),
                                         torch.randn(w.shape[0], rank, generator=g))
    return out


def expected_merge(model, lora, scale):
    state = {k: v.clone() for k, v in model.state_dict().items()}
    for module, (a, b) in lora.items():
        state[module + ".weight"] = state[module + ".weight"] + scale * (b @ a)
    return state


def assert_state(model, expected, atol=1e-6):
    got = model.state_dict()
    assert set(got) == set(expected)
    for k in expected:
        torch.testing.assert_close(got[k], expected[k], atol=atol, rtol=1e-5, msg=k)


def diffsynth_module(module: str) -> str:
    _, index, rest = module.split(".", 2)
    return f"blocks.{index}.{TARGETS[rest]}"


def test_diffsynth_peft_named_lora_merges_as_w_plus_b_a(tmp_path):
    model = transformer()
    lora = random_lora(model, rank=3)
    tensors = {}
    for module, (a, b) in lora.items():  # DiffSynth saves peft's parameter names, adapter "default" included
        tensors[f"{diffsynth_module(module)}.lora_A.default.weight"] = a
        tensors[f"{diffsynth_module(module)}.lora_B.default.weight"] = b
    save_file(tensors, tmp_path / "step-500.safetensors")
    expected = expected_merge(model, lora, 1.0)  # no alpha in the file: DiffSynth merges B A with alpha 1

    found = load.detect_file(tmp_path / "step-500.safetensors")
    assert (found["kind"], found["naming"], found["reader"]) == ("lora", "diffsynth", "rigidbench")
    record = load.apply_file(model, found)
    assert record["lora_layers"] == 2 * len(TARGETS) and record["rank"] == 3 and record["scale"] == 1.0
    assert_state(model, expected)


def test_kohya_down_up_alpha_lora_uses_alpha_over_rank(tmp_path):
    model = transformer()
    lora = random_lora(model, rank=4, seed=2)
    tensors = {}
    for module, (a, b) in lora.items():
        name = f"diffusion_model.{diffsynth_module(module)}"
        tensors[f"{name}.lora_down.weight"] = a
        tensors[f"{name}.lora_up.weight"] = b
        tensors[f"{name}.alpha"] = torch.tensor(2.0)
    save_file(tensors, tmp_path / "kohya.safetensors")
    expected = expected_merge(model, lora, 2.0 / 4)
    load.merge_lora(model, tmp_path / "kohya.safetensors")
    assert_state(model, expected)


def _fake_lightning_attribute_dict():
    """A stand-in for Lightning's AttributeDict, pickled under Lightning's module path."""
    module = types.ModuleType("lightning.fabric.utilities.data")

    class AttributeDict(dict):
        pass

    AttributeDict.__module__, AttributeDict.__qualname__ = module.__name__, "AttributeDict"
    module.AttributeDict = AttributeDict
    return module


def test_the_releases_lightning_lora_checkpoint_loads_with_its_alpha(tmp_path, monkeypatch):
    model = transformer()
    lora = random_lora(model, rank=2, seed=3)
    state = {}
    for module, (a, b) in lora.items():  # LightningModule.state_dict(): "dit." + peft names, lora_ tensors only
        state[f"dit.{diffsynth_module(module)}.lora_A.default.weight"] = a.to(torch.bfloat16)
        state[f"dit.{diffsynth_module(module)}.lora_B.default.weight"] = b.to(torch.bfloat16)
    fake = _fake_lightning_attribute_dict()
    for name in ("lightning", "lightning.fabric", "lightning.fabric.utilities"):
        monkeypatch.setitem(sys.modules, name, types.ModuleType(name))
    monkeypatch.setitem(sys.modules, fake.__name__, fake)
    hparams = fake.AttributeDict(lora={"rank": 2, "alpha": 8, "target_modules": ["q", "k", "v", "o", "ffn.0", "ffn.2"]},
                                 lr=1e-4)
    torch.save({"epoch": 3, "global_step": 1000, "pytorch-lightning_version": "2.6.1", "state_dict": state,
                "hyper_parameters": hparams, "optimizer_states": [{"state": {}, "param_groups": []}]},
               tmp_path / "ckpt-001000.ckpt")
    monkeypatch.delitem(sys.modules, fake.__name__)  # reading must not need Lightning
    lora_bf16 = {k: (a.to(torch.bfloat16).float(), b.to(torch.bfloat16).float()) for k, (a, b) in lora.items()}
    expected = expected_merge(model, lora_bf16, 8 / 2)

    found = load.detect_file(tmp_path / "ckpt-001000.ckpt")
    assert (found["kind"], found["container"], found["reader"]) == ("lora", "lightning", "rigidbench")
    record = load.apply_file(model, found)
    assert record["scale"] == 4.0
    assert_state(model, expected, atol=1e-5)


@pytest.mark.parametrize("fmt", ["safetensors", "pt", "lightning"])
def test_a_full_state_dict_with_diffsynth_names_loads_exactly(tmp_path, fmt):
    source = transformer(seed=7)
    tensors = {diffsynth_key(k): v.clone().contiguous() for k, v in source.state_dict().items()}
    assert "blocks.1.modulation" in tensors and "head.head.weight" in tensors and "blocks.0.norm3.weight" in tensors
    if fmt == "safetensors":
        path = tmp_path / "full.safetensors"
        save_file(tensors, path)
    elif fmt == "pt":
        path = tmp_path / "full.pt"
        torch.save({f"model.{k}": v for k, v in tensors.items()}, path)
    else:
        path = tmp_path / "ckpt-002500.ckpt"
        torch.save({"state_dict": {f"dit.{k}": v for k, v in tensors.items()}, "hyper_parameters": {"lr": 2e-5},
                    "pytorch-lightning_version": "2.6.1"}, path)
    model = transformer(seed=0)
    assert not torch.equal(model.proj_out.weight, source.proj_out.weight)
    found = load.detect_file(path)
    assert found["kind"] == "transformer-state-dict" and found["naming"] == "diffsynth"
    load.apply_file(model, found)
    assert_state(model, source.state_dict(), atol=0)


def test_bad_files_give_errors_naming_the_file(tmp_path):
    model = transformer()
    (tmp_path / "garbage.safetensors").write_bytes(b"not a safetensors file")
    torch.save([1, 2, 3], tmp_path / "list.pt")
    save_file({"blocks.0.self_attn.nothing.lora_A.weight": torch.zeros(2, 16),
               "blocks.0.self_attn.nothing.lora_B.weight": torch.zeros(16, 2)}, tmp_path / "other.safetensors")
    save_file({"blocks.0.self_attn.q.weight": torch.zeros(16, 16)}, tmp_path / "partial.safetensors")
    save_file({"blocks.0.self_attn.q.lora_A.weight": torch.zeros(2, 16)}, tmp_path / "half.safetensors")
    (tmp_path / "weights.npz").write_bytes(b"")
    cases = {"garbage.safetensors": "not a readable safetensors file",
             "list.pt": "holds a list, expected a dict of tensors",
             "other.safetensors": "could not be loaded into the Wan transformer",
             "partial.safetensors": "does not match the Wan transformer: keys",
             "half.safetensors": "has no B",
             "weights.npz": "unknown file type"}
    before = {k: v.clone() for k, v in model.state_dict().items()}
    for name, message in cases.items():
        with pytest.raises(UserError, match=message) as err:
            load.apply_file(model, load.detect_file(tmp_path / name))
        assert str(tmp_path / name) in str(err.value)
    assert_state(model, before, atol=0)  # a refused file changes nothing


def test_wan_predictor_and_probe_backbone_load_a_diffsynth_lora_file(tmp_path):
    """The call sites: predict --checkpoint (detect_checkpoint + load_lora) and probe --backbone."""
    pytest.importorskip("peft")
    from rigidbench.predictors import wan
    from rigidbench.probe.model import load_backbone
    from rigidbench.train import tiny

    base = tiny.tiny_transformer()
    lora = random_lora(base, rank=2, seed=5)
    save_file({f"{diffsynth_module(m)}.lora_{s}.default.weight": t for m, (a, b) in lora.items()
               for s, t in (("A", a), ("B", b))}, tmp_path / "lora.safetensors")
    expected = expected_merge(base, lora, 1.0)

    found = wan.detect_checkpoint(tmp_path / "lora.safetensors")
    assert found["kind"] == "lora"
    backbone = load_backbone(str(tmp_path / "lora.safetensors"), "tiny", None, "cpu")
    assert_state(backbone, expected)

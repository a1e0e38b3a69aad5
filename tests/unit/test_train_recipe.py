"""The fine-tuning recipe options that reproduce the authors' release (docs/finetuning.md): the prompt
and padding of the text context, the clean slot's timestep, shared draws across ranks, bfloat16
timestep/target precision, the learning-rate index of the first update, bfloat16 master weights,
and keep_training_states keeping only the newest resumable state by default."""

import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("diffusers")
pytest.importorskip("peft")

from rigidbench.errors import ConfigError  # noqa: E402
from rigidbench.train.cache import CacheWriter, LatentCache  # noqa: E402
from rigidbench.train.config import load_train_config  # noqa: E402
from rigidbench.train.objective import FlowMatchingObjective  # noqa: E402
from rigidbench.train.schedules import lr_factor, shifted_sigmas, training_timesteps  # noqa: E402

TEXT_LEN, DIM = 12, 32


def synthetic_cache(path, n=4, rows=TEXT_LEN, task_prompt=True):
    """A tiny-model cache: two prompts (with / without the suffix) with ``rows`` stored rows of which 5 / 3
    are real tokens; ``rows`` < TEXT_LEN and no task prompt make it look like a version-1 cache."""
    settings = {"model": "tiny", "width": 128, "height": 64, "frames": 9, "text_len": TEXT_LEN,
                "prompt_format": "synthetic"}
    writer = CacheWriter(path, settings)
    g = torch.Generator().manual_seed(0)
    texts = {"ks": torch.randn(rows, DIM, generator=g), "kt": torch.randn(rows, DIM, generator=g)}
    writer.add_text(texts, {"ks": "A ball falls. Static shot.", "kt": "A ball falls."},
                    {"ks": min(5, rows), "kt": min(3, rows)})
    writer.set(text_dim=DIM, latent_shape=[48, 3, 4, 8])
    latents = {f"{i:05d}": torch.randn(48, 3, 4, 8, generator=g) for i in range(n)}
    records = {k: {"prompt": "ks", **({"prompt_task": "kt"} if task_prompt else {})} for k in latents}
    writer.add_latents(latents, records)
    return path, texts


def tiny(*overrides):
    return load_train_config("tiny", overrides=list(overrides))


def test_the_paper_configs_follow_the_release_where_the_paper_is_silent():
    for name in ("lora", "full", "tiny"):
        cfg = load_train_config(name)
        assert (cfg.text_prompt, cfg.text_padding) == ("task", "encoder")
        objective = (cfg.objective_clean_slot_timestep, cfg.objective_draws, cfg.objective_dtype)
        assert objective == ("noisy", "shared", "bfloat16")
        assert cfg.schedule_first_step == 0
        # the reproduction recipe: the release trained bf16 weights under Lightning's "bf16-mixed"; tiny keeps float32
        assert cfg.master_weights == ("float32" if name == "tiny" else "bfloat16")
        assert cfg.keep_training_states == 1
    cfg = tiny("text.prompt=task+suffix", "text.padding=zeros", "objective.clean_slot_timestep=zero",
               "objective.draws=per_rank", "objective.dtype=float32", "schedule.first_step=1",
               "master_weights=bfloat16")
    assert cfg.to_dict()["text"] == {"prompt": "task+suffix", "padding": "zeros"}
    assert cfg.digest() != tiny().digest()  # a resumed run must keep them
    for bad in ("text.prompt=suffix", "objective.draws=rank", "schedule.first_step=2", "schedule.first_step=true",
                "master_weights=fp16"):
        with pytest.raises(ConfigError):
            tiny(bad)


def test_clean_slot_timestep_noisy_gives_every_token_t_and_zero_pins_slot_zero():
    z, noise = torch.randn(2, 4, 3, 4, 8), torch.randn(2, 4, 3, 4, 8)
    noisy = FlowMatchingObjective(clean_slot_timestep="noisy").prepare(z, noise, 500)
    assert noisy.timestep_tokens.shape == (2,) and noisy.timestep_tokens.eq(noisy.timestep).all()
    zero = FlowMatchingObjective(clean_slot_timestep="zero").prepare(z, noise, 500)
    tokens = zero.timestep_tokens.reshape(2, 3, 8)
    assert tokens[:, 0].eq(0).all() and tokens[:, 1:].eq(zero.timestep).all()
    assert torch.equal(noisy.noisy, zero.noisy) and torch.equal(noisy.noisy[:, :, 0], z[:, :, 0])


def test_the_two_timestep_modes_give_different_predictions_on_the_tiny_model():
    from rigidbench.train import tiny as tiny_models
    from rigidbench.train.objective import transformer_prediction

    model = tiny_models.tiny_transformer()
    z, noise, text = torch.randn(1, 48, 3, 4, 8), torch.randn(1, 48, 3, 4, 8), torch.randn(1, 6, 32)
    with torch.no_grad():
        a, b = (transformer_prediction(model, FlowMatchingObjective(clean_slot_timestep=m).prepare(z, noise, 300), text)
                for m in ("noisy", "zero"))
    assert not torch.allclose(a[:, :, 1:], b[:, :, 1:])  # slot 0's timestep reaches the other slots via attention


@pytest.mark.parametrize("index", [0, 3, 250, 700, 999])
def test_bfloat16_objective_rounds_t_and_looks_sigma_up_at_the_nearest_grid_timestep(index):
    z, noise = torch.randn(1, 4, 2, 2, 2), torch.randn(1, 4, 2, 2, 2)
    batch = FlowMatchingObjective(dtype="bfloat16", clean_slot_timestep="noisy").prepare(z, noise, index)
    t = training_timesteps()
    rounded = float(torch.tensor(float(t[index])).bfloat16())
    nearest = int(np.argmin(np.abs(t - rounded)))
    assert batch.timestep == rounded and batch.index == index and batch.schedule_index == nearest
    assert batch.sigma == pytest.approx(shifted_sigmas()[nearest])
    for tensor in (batch.noisy, batch.target):  # bfloat16 values held in float32
        assert torch.equal(tensor, tensor.bfloat16().float())
    zb, eb = z.bfloat16(), noise.bfloat16()
    assert torch.equal(batch.target, (eb - zb).float())
    if index == 3:  # t_3 = 999.2 rounds to 1000 in bfloat16: grid index 0's sigma and weight
        assert rounded == 1000.0 and nearest == 0
    full = FlowMatchingObjective(dtype="float32").prepare(z, noise, index)
    assert full.timestep == float(t[index]) and full.schedule_index == index


def test_shared_draws_are_rank_zeros_on_every_rank_and_per_rank_draws_differ():
    from rigidbench.train.trainer import draw_seed

    shared, per_rank = tiny("objective.draws=shared"), tiny("objective.draws=per_rank")
    assert draw_seed(shared, 5, 1, 0) == draw_seed(shared, 5, 1, 3) == draw_seed(per_rank, 5, 1, 0)
    assert draw_seed(per_rank, 5, 1, 0) != draw_seed(per_rank, 5, 1, 3)
    assert draw_seed(shared, 5, 1, 0) != draw_seed(shared, 6, 1, 0)


def test_text_context_prompt_and_padding_options(tmp_path):
    path, texts = synthetic_cache(tmp_path / "cache")
    cache = LatentCache(path)
    _, enc_task = cache.batch([0], prompt="task", padding="encoder")
    _, zero_task = cache.batch([0], prompt="task", padding="zeros")
    _, zero_suffix = cache.batch([1], prompt="task+suffix", padding="zeros")
    assert torch.equal(enc_task[0], texts["kt"].half().float())  # every stored row, padding positions included
    assert torch.equal(zero_task[0, :3], texts["kt"][:3].half().float()) and zero_task[0, 3:].eq(0).all()
    assert torch.equal(zero_suffix[0, :5], texts["ks"][:5].half().float()) and zero_suffix[0, 5:].eq(0).all()
    assert torch.equal(cache.batch([1])[1], zero_suffix)  # the default (probes) is unchanged

    old, _ = synthetic_cache(tmp_path / "v1", rows=4, task_prompt=False)  # real tokens only, suffixed prompt only
    old_cache = LatentCache(old)
    with pytest.raises(ConfigError, match="text.padding=zeros"):
        old_cache.check_text("task+suffix", "encoder")
    with pytest.raises(ConfigError, match="text.prompt=task\\+suffix"):
        old_cache.check_text("task", "zeros")
    old_cache.check_text("task+suffix", "zeros")


def test_training_refuses_a_text_setting_the_cache_cannot_serve(tmp_path):
    from rigidbench.train.trainer import train

    old, _ = synthetic_cache(tmp_path / "v1", rows=4, task_prompt=False)
    with pytest.raises(ConfigError, match="no 'task' prompt"):
        train(tiny("max_steps=1"), old, tmp_path / "run", device="cpu", progress=False)


@pytest.mark.parametrize("mode", ["lora", "full"])
def test_bfloat16_master_weights_train_in_bfloat16(mode):
    from rigidbench.train.distributed import DistInfo
    from rigidbench.train.trainer import build_model

    info = DistInfo(rank=0, world_size=1, local_rank=0, device=torch.device("cpu"), backend=None)
    for master, dtype in (("bfloat16", torch.bfloat16), ("float32", torch.float32)):
        model = build_model(tiny(f"mode={mode}", f"master_weights={master}"), info, use_bf16=False)
        trainable = [p for p in model.parameters() if p.requires_grad]
        assert trainable and all(p.dtype == dtype for p in trainable)


def saved_state(run_dir, step):
    """{key: dtype} of every tensor in a run's resumable state at ``step`` (torch.distributed.checkpoint)."""
    import torch.distributed.checkpoint as dcp

    from rigidbench.train import checkpoint as ckpt

    meta = dcp.FileSystemReader(str(run_dir / ckpt.STATE_DIR / f"step-{step}" / "dcp")).read_metadata()
    return {k: v.properties.dtype for k, v in meta.state_dict_metadata.items() if hasattr(v, "properties")}


def bf16_half_spacing(w):
    """Half the distance from each bfloat16 value to its neighbour away from zero: an update smaller than this
    rounds back to the same value (8 significant bits)."""
    exponent = torch.floor(torch.log2(w.float().abs().clamp_min(2.0 ** -126)))
    return 2.0 ** (exponent - 8)


@pytest.mark.filterwarnings("ignore:torch.distributed is disabled")
def test_the_reproduction_recipe_trains_weights_and_adamw_state_in_bfloat16(tmp_path):
    """The packaged full configuration (the published run's recipe) on the tiny model: one real update at the
    recipe's lr 2e-5 keeps the weights and both AdamW moments in bfloat16, and every weight whose bfloat16
    spacing exceeds twice the update is left exactly unchanged."""
    from rigidbench.train.distributed import DistInfo
    from rigidbench.train.trainer import build_model, train

    recipe = load_train_config("full")
    assert recipe.master_weights == "bfloat16" and recipe.optimizer_lr == 2e-5
    path, _ = synthetic_cache(tmp_path / "cache")
    cfg = tiny("mode=full", f"master_weights={recipe.master_weights}", f"optimizer.lr={recipe.optimizer_lr}",
               "schedule.warmup_steps=0", "schedule.first_step=1", "max_steps=1", "checkpoint_every=1")
    train(cfg, path, tmp_path / "run", device="cpu", progress=False)
    dtypes = saved_state(tmp_path / "run", 1)
    weights = {k: d for k, d in dtypes.items() if k.startswith("model.")}
    moments = {k: d for k, d in dtypes.items() if k.endswith((".exp_avg", ".exp_avg_sq"))}
    assert weights and len(moments) == 2 * len(weights)
    assert set(weights.values()) == set(moments.values()) == {torch.bfloat16}

    import torch.distributed.checkpoint as dcp

    info = DistInfo(rank=0, world_size=1, local_rank=0, device=torch.device("cpu"), backend=None)
    initial = {n: p.detach().clone() for n, p in build_model(cfg, info, use_bf16=False).named_parameters()
               if p.requires_grad}  # the trainer's seeded initial weights
    after = {"model": {n: torch.empty_like(p) for n, p in initial.items()}}
    dcp.load(after, checkpoint_id=str(tmp_path / "run" / "training_state" / "step-1" / "dcp"), no_dist=True)
    w0 = torch.cat([initial[n].flatten() for n in initial])
    w1 = torch.cat([after["model"][n].flatten() for n in initial])
    unchanged = (w1 == w0).float().mean().item()
    lr = recipe.optimizer_lr * lr_factor(1, 0, cfg.schedule_horizon_steps)  # Adam's first update is lr x sign(g)
    predicted = (bf16_half_spacing(w0) > lr).float().mean().item()
    assert 0 < unchanged < 1 and unchanged == pytest.approx(predicted, abs=0.01)


@pytest.mark.parametrize("std, expected", [(0.01, 0.435), (0.05, 0.876)])
def test_at_lr_2e_5_most_bfloat16_weight_updates_round_away(std, expected):
    """The 43-88% of the issue: one AdamW step of the full recipe (lr 2e-5, weight decay 0.01) on weights drawn
    N(0, std^2). In bfloat16 a weight stays put where half its spacing exceeds the update, i.e. |w| >= 2^-7:
    P(|w| >= 2^-7) = 0.435 for std 0.01 and 0.876 for std 0.05. With float32 masters every weight moves."""
    from rigidbench.train.trainer import make_optimizer

    recipe = load_train_config("full")
    g = torch.Generator().manual_seed(0)
    w = std * torch.randn(200_000, generator=g)
    grad = torch.randn(200_000, generator=g)
    fractions = {}
    for dtype in (torch.bfloat16, torch.float32):
        p = torch.nn.Parameter(w.to(dtype))
        before = p.detach().clone()
        p.grad = grad.to(dtype)
        optimizer, _ = make_optimizer([p], recipe)
        optimizer.step()
        assert all(s.dtype == dtype for k, s in optimizer.state[p].items() if k != "step")
        fractions[dtype] = (p.detach() == before).float().mean().item()
    predicted = (bf16_half_spacing(w.bfloat16()) > recipe.optimizer_lr).float().mean().item()
    assert fractions[torch.bfloat16] == pytest.approx(predicted, abs=0.005)
    assert fractions[torch.bfloat16] == pytest.approx(expected, abs=0.01)
    assert fractions[torch.float32] < 1e-3


def test_a_tiny_run_with_the_release_recipe_keeps_only_the_newest_state(tmp_path):
    from rigidbench.train import checkpoint as ckpt
    from rigidbench.train.trainer import train

    path, _ = synthetic_cache(tmp_path / "cache")
    cfg = tiny("max_steps=3", "checkpoint_every=1", "master_weights=bfloat16")
    summary = train(cfg, path, tmp_path / "run", device="cpu", progress=False)
    assert [p.name for p in summary.checkpoints] == ["step-1", "step-2", "step-3"]
    assert all((tmp_path / "run" / "checkpoints" / f"step-{s}" / ckpt.CHECKPOINT_FILE).is_file() for s in (1, 2, 3))
    states = sorted(p.name for p in (tmp_path / "run" / ckpt.STATE_DIR).iterdir())
    assert states == ["step-3"]  # keep_training_states: 1 (a full fine-tuning state is ~60 GB)
    lines = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    base = cfg.optimizer_lr
    # first_step 0: update k runs at schedule index k - 1, the first at lr 0 (transformers' schedule, stepped after)
    assert [r["lr"] for r in lines] == pytest.approx([base * lr_factor(k - 1, 2, 40) for k in (1, 2, 3)])
    assert lines[0]["lr"] == 0.0
    run = json.loads((tmp_path / "run" / "run.json").read_text())[0]
    assert run["master_weights"] == "bfloat16" and run["recipe"]["text"] == {"prompt": "task", "padding": "encoder"}

    other = train(tiny("max_steps=2", "checkpoint_every=1", "keep_training_states=0", "schedule.first_step=1"),
                  path, tmp_path / "run-all", device="cpu", progress=False)
    assert len(other.checkpoints) == 2 and len(list((tmp_path / "run-all" / ckpt.STATE_DIR).iterdir())) == 2
    lines = [json.loads(line) for line in (tmp_path / "run-all" / "metrics.jsonl").read_text().splitlines()]
    assert lines[0]["lr"] == pytest.approx(base * lr_factor(1, 2, 40)) and lines[0]["lr"] > 0


def test_preprocess_keeps_the_padding_rows_and_resizes_like_pil_by_default():
    from PIL import Image

    from rigidbench.train import models
    from rigidbench.train import tiny as tiny_models
    from rigidbench.stages.preprocess import resize_frame

    tokenizer, encoder = tiny_models.tiny_tokenizer(), tiny_models.tiny_text_encoder()
    [(rows, n)] = models.encode_prompts_padded(tokenizer, encoder, ["A ball falls."], 20)
    assert rows.shape == (20, 32) and 0 < n < 20 and rows[n:].abs().sum() > 0  # the encoder's outputs, not zeros
    assert torch.equal(models.encode_prompts(tokenizer, encoder, ["A ball falls."], 20)[0], rows[:n])
    frame = np.random.default_rng(0).integers(0, 256, (64, 96, 3), dtype=np.uint8)
    pil_default = np.asarray(Image.fromarray(frame).resize((48, 32)))  # the release: Image.resize's default filter
    assert np.array_equal(resize_frame(frame, (48, 32), "bicubic"), pil_default)
    assert not np.array_equal(resize_frame(frame, (48, 32), "lanczos"), pil_default)

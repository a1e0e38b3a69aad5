"""Fine-tuning numbers: Wan's shifted sigma schedule and loss weight, the learning-rate schedule, and the
training configurations against the paper's table (appendix D). numpy and yaml only."""

import math

import numpy as np
import pytest
import yaml

from rigidbench.errors import ConfigError
from rigidbench.train.config import load_train_config
from rigidbench.train.schedules import lr_factor, shifted_sigmas, training_timesteps, training_weights


def test_sigmas_are_the_shift_5_map_of_a_uniform_grid_from_1_to_0():
    sigma = shifted_sigmas(1000, 5.0)
    assert sigma.shape == (1000,)
    # s = 1, 0.75, 0.5, 0.25, 0.001: sigma = 5s / (1 + 4s)
    assert sigma[0] == pytest.approx(1.0)
    assert sigma[250] == pytest.approx(3.75 / 4.0)
    assert sigma[500] == pytest.approx(2.5 / 3.0)
    assert sigma[750] == pytest.approx(1.25 / 2.0)
    assert sigma[999] == pytest.approx(0.005 / 1.004)
    assert np.all(np.diff(sigma) < 0)
    assert training_timesteps(1000, 5.0)[500] == pytest.approx(2500 / 3)


def test_weight_is_the_normalised_gaussian_bump_centred_at_500():
    w = training_weights(1000, 5.0)
    # by hand, independently of the implementation: b(t) = exp(-2((t-500)/1000)^2) - min over the grid
    t = [1000 * 5 * (1 - i / 1000) / (1 + 4 * (1 - i / 1000)) for i in range(1000)]
    g = [math.exp(-2 * ((x - 500) / 1000) ** 2) for x in t]
    b = [x - min(g) for x in g]
    expected = [1000 * x / sum(b) for x in b]
    assert np.allclose(w, expected, rtol=1e-12)
    assert w.mean() == pytest.approx(1.0)
    # the lowest bump value on the grid is at t = 1000 (pure noise, i = 0), whose weight is exactly 0
    assert w[0] == 0.0
    # ratios need no normalisation: w(t_500) / w(t_750) = (g(833.3) - g(1000)) / (g(625) - g(1000))
    g1000 = math.exp(-0.5)
    assert w[500] / w[750] == pytest.approx((math.exp(-2 * (1000 / 3 / 1000) ** 2) - g1000)
                                            / (math.exp(-2 * 0.125 ** 2) - g1000))
    # the maximum is at the grid point nearest t = 500 (s = 1/9, i = 889)
    assert int(np.argmax(w)) == int(np.argmin(np.abs(training_timesteps() - 500)))


def test_learning_rate_warms_up_linearly_then_follows_a_cosine_to_zero():
    assert lr_factor(1, 250, 5000) == pytest.approx(1 / 250)
    assert lr_factor(125, 250, 5000) == pytest.approx(0.5)
    assert lr_factor(250, 250, 5000) == 1.0
    assert lr_factor(2625, 250, 5000) == pytest.approx(0.5)
    assert lr_factor(5000, 250, 5000) == pytest.approx(0.0)
    assert lr_factor(6000, 250, 5000) == pytest.approx(0.0)
    # the full configuration stops at its horizon
    assert lr_factor(3000, 150, 3000) == pytest.approx(0.0)


def test_lora_and_full_configurations_are_the_papers_table():
    lora, full = load_train_config("lora"), load_train_config("full")
    assert (lora.mode, lora.lora_rank, lora.lora_alpha, lora.lora_dropout) == ("lora", 32, 32.0, 0.0)
    assert lora.lora_target_modules == ("to_q", "to_k", "to_v", "to_out.0", "ffn.net.0.proj", "ffn.net.2")
    assert (lora.distributed, lora.batch_size, lora.grad_accum, lora.effective_batch) == ("ddp", 2, 8, 128)
    assert (lora.optimizer_lr, lora.schedule_horizon_steps, lora.schedule_warmup_steps) == (1e-4, 5000, 250)
    assert lora.gradient_checkpointing is False
    assert (full.mode, full.frozen_modules, full.distributed) == ("full", ("condition_embedder",), "fsdp")
    assert (full.batch_size, full.grad_accum, full.effective_batch) == (16, 1, 128)
    assert (full.optimizer_lr, full.schedule_horizon_steps, full.schedule_warmup_steps) == (2e-5, 3000, 150)
    assert full.gradient_checkpointing is True
    for cfg in (lora, full):
        assert cfg.model == "wan-2.2" and cfg.gpus == 8
        assert (cfg.optimizer_fused, cfg.optimizer_betas, cfg.optimizer_weight_decay, cfg.optimizer_eps) == \
            (True, (0.9, 0.999), 0.01, 1e-8)
        assert (cfg.optimizer_grad_clip, cfg.precision, cfg.seed) == (1.0, "bf16", 42)
        assert (cfg.max_steps, cfg.checkpoint_every) == (3000, 500)
        assert (cfg.objective_num_train_timesteps, cfg.objective_shift) == (1000, 5.0)


def test_overrides_and_typos_in_training_configurations(tmp_path):
    cfg = load_train_config("tiny", overrides=["mode=full", "optimizer.lr=5e-4", "max_steps=3"])
    assert (cfg.mode, cfg.optimizer_lr, cfg.max_steps) == ("full", 5e-4, 3)
    assert "--set mode=full" in cfg.source
    with pytest.raises(ConfigError, match="did you mean 'optimizer.lr'"):
        load_train_config("tiny", overrides=["optimizer.lrr=1"])
    with pytest.raises(ConfigError, match="did you mean 'lora'"):
        load_train_config("lroa")
    with pytest.raises(ConfigError, match="mode"):
        load_train_config("tiny", overrides=["mode=partial"])
    with pytest.raises(ConfigError, match="warmup"):
        load_train_config("tiny", overrides=["schedule.warmup_steps=100", "schedule.horizon_steps=50"])
    # a file of one's own, and a --config directory's train/ copy replacing the packaged one
    own = tmp_path / "mine.yaml"
    own.write_text(yaml.safe_dump(load_train_config("tiny").to_dict()))
    assert load_train_config(own).model == "tiny"
    (tmp_path / "train").mkdir()
    (tmp_path / "train" / "tiny.yaml").write_text(own.read_text().replace("max_steps: 20", "max_steps: 7"))
    assert load_train_config("tiny", [tmp_path]).max_steps == 7
    # the identity of a run leaves out what a resumed run may change
    a, b = load_train_config("tiny"), load_train_config("tiny", overrides=["max_steps=99", "checkpoint_every=3"])
    assert a.digest() == b.digest()
    assert a.digest() != load_train_config("tiny", overrides=["seed=1"]).digest()

"""The DiT side of probing on the tiny Wan transformer: the direct-head readout equals the model's
output at the last block (with and without a subspace removed), and the schedule fractions."""

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("diffusers")

from rigidbench.probe import model as wan  # noqa: E402
from rigidbench.train.objective import FlowMatchingObjective  # noqa: E402


@pytest.fixture(scope="module")
def tiny_setup():
    from rigidbench.train.tiny import tiny_transformer

    transformer = tiny_transformer()
    latent = torch.randn(48, 3, 4, 8, generator=torch.Generator().manual_seed(0))
    text = torch.randn(1, 16, 32, generator=torch.Generator().manual_seed(1))
    return transformer, latent, text


def test_schedule_points_follow_the_release_mapping_tau_09_least_noisy():
    # independent: DiffSynth's training schedule (shift 5, sigma_min 0, extra_one_step) and the release's
    # timestep_by_fraction, idx = round(frac * (len(timesteps) - 1))
    s = np.linspace(1.0, 0.0, 1001)[:-1]
    sigmas = 5 * s / (1 + 4 * s)
    pts = wan.schedule_points(wan.DEFAULT_TAUS)
    for p in pts:
        idx = round(p["tau"] * 999)
        assert p["index"] == idx
        assert p["sigma"] == pytest.approx(sigmas[idx], abs=1e-12)
        assert p["timestep"] == pytest.approx(1000 * sigmas[idx], abs=1e-9)
    assert [p["index"] for p in pts] == [100, 300, 500, 699, 899]
    by_tau = {p["tau"]: p["sigma"] for p in pts}
    assert min(by_tau, key=by_tau.get) == 0.9 and max(by_tau, key=by_tau.get) == 0.1
    assert by_tau[0.9] == pytest.approx(0.3597, abs=1e-4)
    # the noised input at tau 0.9 is closer to the clean latent than at tau 0.1
    latent = torch.randn(48, 3, 4, 8, generator=torch.Generator().manual_seed(0))
    far = wan.noised_batch(latent, "c", 0.1).noisy[0, :, 1:] - latent[:, 1:]
    near = wan.noised_batch(latent, "c", 0.9).noisy[0, :, 1:] - latent[:, 1:]
    assert float(near.norm()) < 0.5 * float(far.norm())


def test_noised_batch_keeps_slot_zero_clean_and_noise_is_per_clip(tiny_setup):
    _, latent, _ = tiny_setup
    batch = wan.noised_batch(latent, "00001", 0.5)
    assert torch.equal(batch.noisy[0, :, 0], latent[:, 0])
    tokens = batch.timestep_tokens.reshape(3, 8)
    assert (tokens[0] == 0).all() and torch.allclose(tokens[1:], torch.full_like(tokens[1:], batch.timestep))
    assert torch.equal(wan.clip_noise("a", (2, 3)), wan.clip_noise("a", (2, 3)))
    assert not torch.equal(wan.clip_noise("a", (2, 3)), wan.clip_noise("b", (2, 3)))


def test_direct_head_and_full_model_coincide_at_the_last_block(tiny_setup):
    transformer, latent, text = tiny_setup
    obj = FlowMatchingObjective()
    batch = wan.noised_batch(latent, "00001", 0.5, obj)
    store = {}
    with torch.no_grad(), wan.capture_blocks(transformer, store):
        out = wan.forward(transformer, batch, text, "cpu")
    last = len(transformer.blocks) - 1
    assert set(store) == {0, last, "temb"} and store[0].shape == (1, 24, 24)
    with torch.no_grad():
        head = wan.direct_head(transformer, store[last], store["temb"], batch.noisy.shape)
    assert torch.allclose(head, out, atol=1e-6)
    basis = torch.as_tensor(np.linalg.qr(np.random.default_rng(0).standard_normal((24, 5)))[0], dtype=torch.float32)
    with torch.no_grad():
        with wan.intervene_block(transformer, last, basis, 1.0):
            full = wan.forward(transformer, batch, text, "cpu")
        h = store[last]
        direct = wan.direct_head(transformer, h - (h @ basis) @ basis.T, store["temb"], batch.noisy.shape)
    assert torch.allclose(full, direct, atol=1e-6)
    assert wan.flow_loss(full, batch) != pytest.approx(wan.flow_loss(out, batch))
    # the hook is removed afterwards
    with torch.no_grad():
        assert torch.allclose(wan.forward(transformer, batch, text, "cpu"), out)


def test_random_backbone_is_seeded_and_resets_what_the_release_resets():
    base = wan.load_backbone("base", "tiny", None, "cpu").state_dict()
    a = wan.load_backbone("random", "tiny", None, "cpu", seed=0).state_dict()
    b = wan.load_backbone("random", "tiny", None, "cpu", seed=0).state_dict()
    c = wan.load_backbone("random", "tiny", None, "cpu", seed=1).state_dict()
    assert a.keys() == base.keys()
    assert all(torch.equal(a[k], b[k]) for k in a)           # same seed: identical
    kept = [k for k in a if k.endswith("scale_shift_table") or ".norm_q." in k or ".norm_k." in k]
    linear = [k for k in a if k.endswith(".weight") and a[k].ndim >= 2]
    assert kept and len(linear) > 10
    for k in kept:  # the modulation tables and the query/key RMS norms keep their pretrained values
        assert torch.equal(a[k], base[k]) and torch.equal(c[k], base[k]), k
    for k in linear:  # every linear and convolution weight is re-drawn, differently per seed
        assert not torch.equal(a[k], base[k]) and not torch.equal(a[k], c[k]), k
        bound = 1 / np.sqrt(np.prod(a[k].shape[1:]))  # PyTorch's default init: U(-1/sqrt(fan_in), +)
        assert float(a[k].abs().max()) <= bound + 1e-6


def test_random_backbone_resets_affine_layer_norms_of_a_trained_model():
    from rigidbench.train.tiny import tiny_transformer

    trained = tiny_transformer()
    with torch.no_grad():
        for p in trained.parameters():
            p.add_(0.5)
    before = {k: v.clone() for k, v in trained.state_dict().items()}
    after = wan.reset_parameters(trained, seed=3).state_dict()
    assert torch.equal(after["blocks.0.norm2.weight"], torch.ones_like(before["blocks.0.norm2.weight"]))
    assert torch.equal(after["blocks.0.norm2.bias"], torch.zeros_like(before["blocks.0.norm2.bias"]))
    assert torch.equal(after["blocks.0.attn1.norm_q.weight"], before["blocks.0.attn1.norm_q.weight"])
    assert torch.equal(after["scale_shift_table"], before["scale_shift_table"])
    # the global RNG is left as it was
    torch.manual_seed(11)
    x = torch.rand(3)
    torch.manual_seed(11)
    wan.reset_parameters(tiny_transformer(), seed=3)
    assert torch.equal(torch.rand(3), x)


def test_checkpoint_backbone_loads_a_saved_transformer_directory(tmp_path):
    from rigidbench.train.tiny import tiny_transformer

    saved = tiny_transformer(seed=7)
    saved.save_pretrained(tmp_path / "step-1")
    loaded = wan.load_backbone(str(tmp_path / "step-1"), "tiny", None, "cpu")
    assert torch.equal(loaded.proj_out.weight, saved.proj_out.weight)


def test_store_splits_follow_the_paper_proportions():
    from rigidbench.probe.store import assign_splits

    big = assign_splits([f"{i:05d}" for i in range(5000)])
    assert sorted(list(big.values()).count(s) for s in ("train", "val", "test")) == [500, 500, 4000]
    assert sorted(assign_splits(["a", "b", "c", "d"]).values()) == ["test", "train", "train", "val"]
    assert list(assign_splits(["a", "b"]).values()) == ["train", "train"]


def test_user_errors_exit_with_status_2(tmp_path, capsys):
    from rigidbench.cli import main

    assert main(["probe", "fit", "--acts", str(tmp_path), "--out", str(tmp_path / "p")]) == 2
    assert "not an activation store" in capsys.readouterr().err
    assert main(["probe", "report", "--out", str(tmp_path / "r")]) == 2


def test_resuming_from_a_block_equals_a_forward_hook_at_every_block(tiny_setup):
    transformer, latent, text = tiny_setup
    batch = wan.noised_batch(latent, "00002", 0.3)
    store = {}
    with torch.no_grad(), wan.capture_blocks(transformer, store), wan.capture_block_inputs(transformer, store):
        out = wan.forward(transformer, batch, text, "cpu")
    basis = torch.as_tensor(np.linalg.qr(np.random.default_rng(1).standard_normal((24, 4)))[0], dtype=torch.float32)
    for block in range(len(transformer.blocks)):
        with torch.no_grad():
            h = store[block]
            assert torch.allclose(wan.resume_from(transformer, block, h, store["block_args"], store["temb"],
                                                  batch.noisy.shape), out, atol=1e-6)
            with wan.intervene_block(transformer, block, basis, 0.7):
                hooked = wan.forward(transformer, batch, text, "cpu")
            resumed = wan.resume_from(transformer, block, h - 0.7 * (h @ basis) @ basis.T, store["block_args"],
                                      store["temb"], batch.noisy.shape)
        assert torch.allclose(hooked, resumed, atol=1e-6)
        assert not torch.allclose(hooked, out, atol=1e-4)


def test_release_conditioning_rounds_timesteps_to_bfloat16_and_shares_the_noise(tiny_setup):
    from rigidbench.probe.recipe import RECIPES, Conditioning

    release = RECIPES["release"].conditioning
    # independent: DiffSynth's training grid, the timestep cast to bfloat16 as the release's
    # timestep_by_fraction(frac).to(bfloat16), and the scheduler's argmin lookup of sigma
    s = np.linspace(1.0, 0.0, 1001)[:-1]
    grid = 1000 * 5 * s / (1 + 4 * s)
    rounded = [float(torch.tensor(grid[round(t * 999)], dtype=torch.float32).to(torch.bfloat16))
               for t in wan.DEFAULT_TAUS]
    used = [int(np.argmin(np.abs(grid - t))) for t in rounded]
    assert used == [93, 303, 502, 698, 899]
    pts = wan.schedule_points(wan.DEFAULT_TAUS, wan.make_objective(release))
    assert [p["schedule_index"] for p in pts] == used and [p["index"] for p in pts] == [100, 300, 500, 699, 899]
    assert [p["timestep"] for p in pts] == rounded
    assert [p["sigma"] for p in pts] == pytest.approx([grid[i] / 1000 for i in used], abs=1e-12)
    assert "schedule_index" not in wan.schedule_points([0.1])[0]  # ours: the exact grid timestep
    _, latent, _ = tiny_setup
    for n, tau in enumerate(wan.DEFAULT_TAUS):
        batch = wan.noised_batch(latent, "00001", tau, conditioning=release)
        assert batch.timestep_tokens.shape == (1,) and float(batch.timestep_tokens[0]) == rounded[n]
        assert batch.schedule_index == used[n]
        # bfloat16 noised latent from the shared noise (a generator seeded 0, whatever the clip)
        eps = torch.randn((1, *latent.shape), generator=torch.Generator().manual_seed(0)).to(torch.bfloat16)
        z = latent.unsqueeze(0).to(torch.bfloat16)
        sigma = grid[used[n]] / 1000
        assert torch.equal(batch.noisy[:, :, 1:], ((1 - sigma) * z + sigma * eps)[:, :, 1:].float())
        assert torch.equal(batch.noisy[:, :, 0], z[:, :, 0].float())
    ours = wan.noised_batch(latent, "00001", 0.5)
    assert ours.timestep_tokens.shape == (1, 24) and ours.schedule_index == 500
    # the clean slot's timestep alone: t on slot 0's tokens instead of 0
    noisy_slot = wan.noised_batch(latent, "00001", 0.5, conditioning=Conditioning(clean_slot_timestep="noisy"))
    assert noisy_slot.timestep_tokens.tolist() == pytest.approx([ours.timestep], abs=1e-4)
    assert torch.equal(noisy_slot.noisy, ours.noisy) and float(ours.timestep_tokens[0, 0]) == 0.0
    # shared noise is one tensor for every clip; per-clip noise differs between clips
    shape = (1, *latent.shape)
    assert torch.equal(wan.noise_for("a", shape, 0, release), wan.noise_for("b", shape, 0, release))
    assert not torch.equal(wan.noise_for("a", shape), wan.noise_for("b", shape))
    assert torch.equal(wan.noise_for("a", shape), wan.clip_noise("a", shape))


def test_conditioning_choices_are_checked_and_recipes_compose():
    from rigidbench.errors import UserError
    from rigidbench.probe.recipe import RECIPES, Conditioning, conditioning_with, recipe, recipe_label

    with pytest.raises(UserError, match="prompt must be one of task\\+suffix, task"):
        Conditioning(prompt="suffix")
    with pytest.raises(UserError, match="unknown probe recipe 'paper'"):
        recipe("paper")
    release = recipe("release")
    assert release.inlp == "release" and recipe(None).name == "ours" and Conditioning().key_part() is None
    assert release.conditioning.as_dict() == {"prompt": "task", "padding": "encoder", "clean_slot_timestep": "noisy",
                                              "dtype": "bfloat16", "objective_dtype": "bfloat16", "noise": "shared"}
    changed = conditioning_with(release.conditioning, noise="per-clip", dtype=None)
    assert changed.noise == "per-clip" and changed.dtype == "bfloat16"
    assert recipe_label("release", changed) == "release+changes" and recipe_label("release", RECIPES[
        "release"].conditioning) == "release"
    assert Conditioning.from_record(None) == Conditioning()

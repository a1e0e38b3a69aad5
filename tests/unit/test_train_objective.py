"""The fine-tuning objective (appendix D): noised latent and velocity target, first-slot pinning as
the TI2V pipeline does it at inference, the weighted float32 MSE without slot 0, and the seeded draws."""

import pytest

torch = pytest.importorskip("torch")

from rigidbench.train.objective import FlowMatchingObjective, transformer_prediction  # noqa: E402
from rigidbench.train.trainer import DataOrder, stream_seed  # noqa: E402

SHAPE = (2, 48, 3, 4, 8)  # (B, C, F, h, w): 3 latent slots on a 4x8 grid -> 3 x 2 x 4 tokens


class Spy(torch.nn.Module):
    """Stands in for the transformer: records its inputs and returns a fixed prediction."""

    def __init__(self, prediction):
        super().__init__()
        self.prediction = prediction
        self.calls = []

    def forward(self, hidden_states, timestep, encoder_hidden_states, return_dict=False):
        self.calls.append({"hidden_states": hidden_states, "timestep": timestep, "text": encoder_hidden_states})
        return (self.prediction,)


def draw(index=None, seed=0):
    objective = FlowMatchingObjective(1000, 5.0)
    g = torch.Generator().manual_seed(seed)
    z = torch.randn(SHAPE, generator=g)
    i, noise = objective.draw(g, SHAPE)
    return objective, z, noise, (i if index is None else index)


def test_noised_latent_and_velocity_target_are_the_flow_matching_pair():
    objective, z, noise, _ = draw()
    batch = objective.prepare(z, noise, 500)
    sigma = 5 * 0.5 / (1 + 4 * 0.5)
    assert batch.sigma == pytest.approx(sigma) and batch.timestep == pytest.approx(1000 * sigma)
    assert batch.weight == pytest.approx(float(objective.weights[500]))
    assert torch.allclose(batch.noisy[:, :, 1:], (1 - sigma) * z[:, :, 1:] + sigma * noise[:, :, 1:])
    assert torch.equal(batch.target, noise - z)
    assert batch.noisy.dtype == batch.target.dtype == torch.float32


def test_the_first_slot_enters_the_model_clean_at_timestep_zero():
    objective, z, noise, index = draw()
    batch = objective.prepare(z, noise, 100)
    spy = Spy(torch.zeros(SHAPE))
    transformer_prediction(spy, batch, torch.zeros(2, 16, 32))
    seen = spy.calls[0]
    assert torch.equal(seen["hidden_states"][:, :, 0], z[:, :, 0])  # the clean latent, bit for bit
    assert not torch.allclose(seen["hidden_states"][:, :, 1], z[:, :, 1])  # later slots are noised
    # per-token timesteps exactly as WanImageToVideoPipeline builds them with expand_timesteps
    mask = torch.ones(1, 1, 3, 4, 8)
    mask[:, :, 0] = 0
    expected = (mask[0][0][:, ::2, ::2] * batch.timestep).flatten().unsqueeze(0).expand(2, -1)
    assert seen["timestep"].shape == (2, 24)
    assert torch.equal(seen["timestep"], expected)


def test_the_loss_ignores_the_first_slot_of_the_prediction_and_is_weighted_float32_mse():
    objective, z, noise, _ = draw(seed=3)
    batch = objective.prepare(z, noise, 700)
    pred = torch.randn(SHAPE, generator=torch.Generator().manual_seed(1))
    loss = objective.loss(pred, batch)
    altered = pred.clone()
    altered[:, :, 0] = 1e6
    assert objective.loss(altered, batch) == loss
    by_hand = batch.weight * ((pred[:, :, 1:].double() - (noise - z)[:, :, 1:].double()) ** 2).mean()
    assert float(loss) == pytest.approx(float(by_hand), rel=1e-6)
    assert objective.loss(pred.to(torch.bfloat16), batch).dtype == torch.float32
    # and a different later slot does change it
    altered[:, :, 1] += 1
    assert objective.loss(altered, batch) != loss


def test_draws_are_uniform_indices_and_reproducible_per_seed():
    objective = FlowMatchingObjective(1000, 5.0)
    a = objective.draw(torch.Generator().manual_seed(stream_seed(42, 7, 0, 0)), SHAPE)
    b = objective.draw(torch.Generator().manual_seed(stream_seed(42, 7, 0, 0)), SHAPE)
    c = objective.draw(torch.Generator().manual_seed(stream_seed(42, 7, 0, 1)), SHAPE)
    assert a[0] == b[0] and torch.equal(a[1], b[1]) and not torch.equal(a[1], c[1])
    indices = [objective.draw(torch.Generator().manual_seed(s), (1,))[0] for s in range(4000)]
    assert min(indices) >= 0 and max(indices) <= 999
    counts = torch.bincount(torch.tensor(indices) // 250, minlength=4)
    assert counts.min() > 900  # about 1000 per quarter


def test_data_order_is_a_fresh_permutation_per_pass():
    order = DataOrder(5, seed=42)
    first, second = [order(p) for p in range(5)], [order(p) for p in range(5, 10)]
    assert sorted(first) == sorted(second) == list(range(5))
    assert [DataOrder(5, 42)(p) for p in range(10)] == first + second
    assert [DataOrder(5, 43)(p) for p in range(10)] != first + second

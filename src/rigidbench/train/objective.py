"""The fine-tuning objective of the paper's appendix D (equations "finetuning-noise" and
"finetuning-loss"), as Wan 2.2 TI2V-5B is trained and sampled with ``expand_timesteps``:

    i ~ U{0 .. N-1}, one per local batch;  sigma = sigma_i, t = t_i   (schedules.py)
    z_t = (1 - sigma) z + sigma eps;         v = eps - z              (noised latent, velocity target)
    z_t[:, :, 0] = z[:, :, 0]                                          (first temporal slot clean ...)
    timestep per token = t, and 0 on the tokens of the first slot     (... and at timestep 0)
    L = w_i * MSE(f(z_t, t, c)[:, :, 1:], v[:, :, 1:])                 (float32; slot 0 left out)

The per-token timestep is what ``WanImageToVideoPipeline`` passes at inference with
``expand_timesteps`` (its ``first_frame_mask[0][0][:, ::2, ::2] * t``: one value per patch of the
(1, 2, 2) patch grid). The timestep is the float t_i, as in Wan's training code.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from .schedules import shifted_sigmas, training_timesteps, training_weights


@dataclass
class NoisedBatch:
    """One local batch prepared for the transformer. latents, noisy, target: (B,C,F,H,W) float32;
    timestep_tokens: (B, F*H/ph*W/pw) float32; index: the drawn timestep index; sigma, timestep,
    weight: its sigma, timestep and loss weight."""

    latents: torch.Tensor
    noisy: torch.Tensor
    target: torch.Tensor
    timestep_tokens: torch.Tensor
    index: int
    sigma: float
    timestep: float
    weight: float


class FlowMatchingObjective:
    """Wan's flow-matching training objective with first-slot pinning (see the module docstring)."""

    def __init__(self, num_train_timesteps: int = 1000, shift: float = 5.0, patch_size=(1, 2, 2)):
        self.num_train_timesteps = num_train_timesteps
        self.shift = shift
        self.patch_size = tuple(int(p) for p in patch_size)
        self.sigmas = shifted_sigmas(num_train_timesteps, shift)
        self.timesteps = training_timesteps(num_train_timesteps, shift)
        self.weights = training_weights(num_train_timesteps, shift)

    def draw(self, generator: torch.Generator, latent_shape) -> tuple[int, torch.Tensor]:
        """One timestep index (uniform over the N training timesteps) and Gaussian noise of
        ``latent_shape``, both from ``generator`` (CPU), in that order."""
        index = int(torch.randint(0, self.num_train_timesteps, (1,), generator=generator).item())
        noise = torch.randn(tuple(latent_shape), generator=generator, dtype=torch.float32)
        return index, noise

    def timestep_tokens(self, timestep: float, latent_shape, device=None) -> torch.Tensor:
        """(B, L) float32: ``timestep`` for every patch token, 0 for the tokens of temporal slot 0."""
        b, _, f, h, w = latent_shape
        pt, ph, pw = self.patch_size
        if pt != 1:
            raise ValueError(f"first-slot pinning needs a temporal patch size of 1, got {pt}")
        per_slot = (h // ph) * (w // pw)
        tokens = torch.full((b, f, per_slot), float(timestep), dtype=torch.float32, device=device)
        tokens[:, 0] = 0.0
        return tokens.reshape(b, f * per_slot)

    def prepare(self, latents: torch.Tensor, noise: torch.Tensor, index: int) -> NoisedBatch:
        """latents, noise: (B,C,F,H,W). The noised input with slot 0 restored, the velocity target and
        the per-token timesteps for timestep index ``index``."""
        z = latents.float()
        eps = noise.to(device=z.device, dtype=torch.float32)
        sigma = float(self.sigmas[index])
        noisy = (1.0 - sigma) * z + sigma * eps
        noisy[:, :, 0:1] = z[:, :, 0:1]
        target = eps - z
        timestep = float(self.timesteps[index])
        return NoisedBatch(latents=z, noisy=noisy, target=target,
                           timestep_tokens=self.timestep_tokens(timestep, z.shape, z.device), index=index,
                           sigma=sigma, timestep=timestep, weight=float(self.weights[index]))

    @staticmethod
    def loss(prediction: torch.Tensor, batch: NoisedBatch) -> torch.Tensor:
        """w * float32 MSE over temporal slots 1.. (slot 0 is the clean conditioning frame)."""
        pred = prediction[:, :, 1:].float()
        return batch.weight * torch.nn.functional.mse_loss(pred, batch.target[:, :, 1:])


def transformer_prediction(model, batch: NoisedBatch, text: torch.Tensor, input_dtype=None) -> torch.Tensor:
    """The transformer's velocity prediction for ``batch`` with text context ``text`` (B, L, D)."""
    hidden = batch.noisy if input_dtype is None else batch.noisy.to(input_dtype)
    out = model(hidden_states=hidden, timestep=batch.timestep_tokens, encoder_hidden_states=text,
                return_dict=False)
    return out[0]

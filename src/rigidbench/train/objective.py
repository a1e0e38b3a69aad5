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

Two options reproduce the authors' release (docs/finetuning.md; the class defaults are the above, the
training configurations choose the release's):

- ``clean_slot_timestep="noisy"``: every token, those of the clean slot 0 included, sees the one
  timestep t (the release calls DiffSynth's ``model_fn_wan_video`` without
  ``fuse_vae_embedding_in_latents``, so its timestep is a scalar); the transformer gets a (B,) timestep.
  ``"zero"``: the per-token timesteps above.
- ``dtype="bfloat16"``: the release computes in bfloat16: t_i is rounded to bfloat16 (that is the
  timestep the transformer sees), sigma and w are those of the grid timestep nearest the rounded value
  (DiffSynth looks them up by argmin |t_j - t|), and the noised latent and the target are bfloat16
  (the float32 fields below then hold bfloat16 values). ``"float32"``: as above.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from .schedules import shifted_sigmas, training_timesteps, training_weights


@dataclass
class NoisedBatch:
    """One local batch prepared for the transformer. latents, noisy, target: (B,C,F,H,W) float32;
    timestep_tokens: (B, F*H/ph*W/pw) float32 per token, or (B,) when every token has the same timestep
    (``clean_slot_timestep="noisy"``); index: the drawn timestep index; sigma, timestep, weight: the
    sigma, timestep and loss weight used; schedule_index: the grid index that sigma and weight belong to
    (``index`` except under ``dtype="bfloat16"``, where the rounded timestep may be nearer another)."""

    latents: torch.Tensor
    noisy: torch.Tensor
    target: torch.Tensor
    timestep_tokens: torch.Tensor
    index: int
    sigma: float
    timestep: float
    weight: float
    schedule_index: int = -1


class FlowMatchingObjective:
    """Wan's flow-matching training objective with first-slot pinning (see the module docstring)."""

    def __init__(self, num_train_timesteps: int = 1000, shift: float = 5.0, patch_size=(1, 2, 2),
                 clean_slot_timestep: str = "zero", dtype: str = "float32"):
        if clean_slot_timestep not in ("zero", "noisy"):
            raise ValueError(f"clean_slot_timestep must be 'zero' or 'noisy', got {clean_slot_timestep!r}")
        if dtype not in ("float32", "bfloat16"):
            raise ValueError(f"dtype must be 'float32' or 'bfloat16', got {dtype!r}")
        self.clean_slot_timestep = clean_slot_timestep
        self.dtype = dtype
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
        the timesteps for timestep index ``index`` (see the module docstring for the options)."""
        z = latents.float()
        eps = noise.to(device=z.device, dtype=torch.float32)
        timestep, used = float(self.timesteps[index]), int(index)
        if self.dtype == "bfloat16":
            timestep = float(torch.tensor(timestep, dtype=torch.float32).to(torch.bfloat16))
            used = int(np.argmin(np.abs(self.timesteps - timestep)))
            z, eps = z.to(torch.bfloat16), eps.to(torch.bfloat16)
        sigma = float(self.sigmas[used])
        noisy = (1.0 - sigma) * z + sigma * eps
        noisy[:, :, 0:1] = z[:, :, 0:1]
        target = eps - z
        if self.clean_slot_timestep == "noisy":
            tokens = torch.full((z.shape[0],), timestep, dtype=torch.float32, device=z.device)
        else:
            tokens = self.timestep_tokens(timestep, z.shape, z.device)
        return NoisedBatch(latents=z.float(), noisy=noisy.float(), target=target.float(), timestep_tokens=tokens,
                           index=int(index), sigma=sigma, timestep=timestep, weight=float(self.weights[used]),
                           schedule_index=used)

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

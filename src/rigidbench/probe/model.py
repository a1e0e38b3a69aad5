"""The DiT side of probing: the three backbones, the teacher-forced noised input at a schedule fraction,
block hooks, and Wan's final time-conditioned head applied to any block's output (the direct readout).

Schedule fractions (the paper's "positions tau along the 1,000-step training schedule", mapped as
the release's ``timestep_by_fraction``): tau indexes the training schedule of ``train.schedules`` from
its noisy end, i = round(tau (N - 1)) with Python's round (N = 1,000, timesteps in decreasing order,
s_i = 1 - i/N before the shift-5 warp, sigma_i = 5 s_i / (1 + 4 s_i)). So tau = 0.1 is the noisiest of
the five and tau = 0.9 the least noisy: indices 100, 300, 500, 699, 899 and sigma = 0.978, 0.921,
0.833, 0.683, 0.360 for tau = 0.1, 0.3, 0.5, 0.7, 0.9. The transformer sees timestep N sigma on every
token but those of slot 0, which stay clean at timestep 0 (``train.objective.FlowMatchingObjective
.prepare``, as in training). The noise of a clip is drawn from a CPU generator seeded with a hash of
(seed 0, clip id), the same for every tau, block and backbone. These are the defaults (recipe ``ours``);
``recipe.Conditioning`` names the release's choices (``make_objective``, ``noise_for``): the one timestep on
every token, bfloat16-rounded timesteps (the model sees t rounded to bfloat16, sigma is that of the
schedule timestep nearest it: indices 93, 303, 502, 698, 899 for the five taus), and one noise tensor
shared by every clip (a CPU draw seeded with the seed; the release drew it on the GPU in bfloat16).

Random backbone (the release's ``reset_dit_parameters``): the pretrained DiT with every submodule
that has ``reset_parameters()`` re-initialised, in module order, from one seed: linear and
convolution layers (PyTorch's default init) and the affine cross-attention LayerNorm (weight 1,
bias 0). Parameters outside such modules keep their pretrained values: the modulation tables
(``scale_shift_table``) and the RMS norms of queries and keys (DiffSynth's RMSNorm, which the release
resets through, has no ``reset_parameters``; torch's, used by diffusers, has one and is skipped here
to match). The draws come from a CPU generator seeded ``seed`` (float64, cast to the model's dtype),
so they are the same on every device, not the release's CUDA bfloat16 draws.
"""

from __future__ import annotations

import hashlib
from contextlib import contextmanager
from types import SimpleNamespace

import numpy as np
import torch

from ..errors import UserError
from ..predictors.wan import detect_checkpoint, load_full_transformer, load_lora
from ..train.objective import FlowMatchingObjective
from .recipe import Conditioning

DEFAULT_TAUS = (0.1, 0.3, 0.5, 0.7, 0.9)
NUM_TRAIN_TIMESTEPS = 1000
SHIFT = 5.0
RANDOM_SEED = 0  # the random backbone's default seed (the release's --seed default)
TAU_MAPPING = "index = round(tau * (N - 1)) into the N training timesteps, noisiest first (the release's)"
RANDOM_INIT = ("pretrained DiT; every submodule with reset_parameters() except RMSNorm re-initialised in module "
               "order from a CPU generator (float64 draws); scale_shift_table and RMSNorm weights kept")


def tau_index(tau: float, n: int = NUM_TRAIN_TIMESTEPS) -> int:
    """Index into the N training timesteps (noisiest first) of schedule fraction ``tau``: round(tau (N-1))."""
    if not 0.0 <= tau <= 1.0:
        raise UserError(f"schedule fractions must lie in [0, 1], got {tau}")
    return min(n - 1, max(0, int(round(tau * (n - 1)))))


def effective_step(index: int, objective: FlowMatchingObjective) -> tuple[int, float]:
    """(the schedule index whose sigma is used, the timestep the model sees) at schedule index ``index``:
    ``index`` and its timestep, or under ``objective.dtype == "bfloat16"`` the timestep rounded to
    bfloat16 and the index of the schedule timestep nearest it (``FlowMatchingObjective.prepare``)."""
    t = float(objective.timesteps[index])
    if objective.dtype != "bfloat16":
        return int(index), t
    t = float(torch.tensor(t, dtype=torch.float32).to(torch.bfloat16))
    return int(np.argmin(np.abs(objective.timesteps - t))), t


def schedule_points(taus, objective: FlowMatchingObjective | None = None) -> list[dict]:
    """[{"tau", "index", "sigma", "timestep"}] for the schedule fractions ``taus``: sigma and the timestep
    the model sees; under a bfloat16 objective also "schedule_index", the index that sigma belongs to."""
    obj = objective or FlowMatchingObjective(NUM_TRAIN_TIMESTEPS, SHIFT)
    points = []
    for t in taus:
        index = tau_index(t, obj.num_train_timesteps)
        used, timestep = effective_step(index, obj)
        point = {"tau": float(t), "index": index, "sigma": float(obj.sigmas[used]), "timestep": timestep}
        if obj.dtype == "bfloat16":
            point["schedule_index"] = used
        points.append(point)
    return points


def make_objective(conditioning: Conditioning = Conditioning(), patch_size=(1, 2, 2)) -> FlowMatchingObjective:
    """The training objective that noises the latent under ``conditioning`` (slot-0 timestep, precision)."""
    return FlowMatchingObjective(NUM_TRAIN_TIMESTEPS, SHIFT, patch_size,
                                 clean_slot_timestep=conditioning.clean_slot_timestep,
                                 dtype=conditioning.objective_dtype)


def clip_noise(clip_id: str, shape, seed: int = 0) -> torch.Tensor:
    """Gaussian noise (float32, CPU) of ``shape`` for one clip: a function of (seed, clip id) only."""
    digest = hashlib.sha256(f"{int(seed)}/{clip_id}".encode()).digest()
    gen = torch.Generator().manual_seed(int.from_bytes(digest[:8], "little") & ((1 << 63) - 1))
    return torch.randn(tuple(shape), generator=gen, dtype=torch.float32)


def shared_noise(shape, seed: int = 0) -> torch.Tensor:
    """Gaussian noise (float32, CPU) of ``shape`` from a generator seeded ``seed``: the same for every clip."""
    return torch.randn(tuple(shape), generator=torch.Generator().manual_seed(int(seed)), dtype=torch.float32)


def noise_for(clip_id: str, shape, seed: int = 0, conditioning: Conditioning = Conditioning()) -> torch.Tensor:
    """The noise a clip is noised with under ``conditioning``: per clip, or shared by every clip."""
    return shared_noise(shape, seed) if conditioning.noise == "shared" else clip_noise(clip_id, shape, seed)


def _is_rms_norm(module) -> bool:
    return type(module).__name__ == "RMSNorm"


def reset_parameters(transformer, seed: int = RANDOM_SEED):
    """Re-initialise ``transformer`` in place as the release's random backbone (module docstring);
    returns it. The same seed gives the same weights on every device."""
    with torch.no_grad(), torch.random.fork_rng(devices=[]):
        torch.manual_seed(int(seed))  # the CPU generator; restored afterwards
        for module in transformer.modules():
            if not hasattr(module, "reset_parameters") or _is_rms_norm(module):
                continue
            real = {k: p for k, p in module._parameters.items() if p is not None}
            if not real:
                continue
            # draw into CPU float64 stand-ins, then copy into the real parameters
            for k, p in real.items():
                module._parameters[k] = torch.nn.Parameter(torch.empty(p.shape, dtype=torch.float64))
            try:
                module.reset_parameters()
                fresh = {k: module._parameters[k].detach() for k in real}
            finally:
                for k, p in real.items():
                    module._parameters[k] = p
            for k, p in real.items():
                p.copy_(fresh[k].to(device=p.device, dtype=p.dtype))
    return transformer


def load_backbone(backbone: str, model: str, model_path: str | None, device, dtype=torch.float32,
                  seed: int = RANDOM_SEED):
    """``base``: the pretrained DiT (the tiny builder's seed-0 weights for ``tiny``); ``random``: the base
    DiT re-initialised as the release does (``reset_parameters`` with ``seed``), VAE and token layout
    unchanged; anything else: a checkpoint of ``rigidbench train`` (a full transformer directory, or a
    LoRA adapter applied to the base model)."""
    from ..train import models

    if backbone == "base":
        return models.load_transformer(model, model_path, "pretrained", dtype, device).eval()
    if backbone == "random":
        base = models.load_transformer(model, model_path, "pretrained", dtype, device)
        return reset_parameters(base, seed).eval()
    found = detect_checkpoint(backbone)
    base = models.load_transformer(model, model_path, "pretrained", dtype, device)
    holder = SimpleNamespace(transformer=base, register_modules=lambda **kw: setattr(holder, "transformer",
                                                                                       kw["transformer"]))
    if found["kind"].startswith("lora"):
        load_lora(holder, found)
    else:
        load_full_transformer(holder, found)
    return holder.transformer.to(device).eval()


def noised_batch(latent: torch.Tensor, clip_id: str, tau: float, objective: FlowMatchingObjective | None = None,
                 seed: int = 0, conditioning: Conditioning = Conditioning()):
    """latent (C, F, h, w) -> the objective's NoisedBatch (B = 1) at schedule fraction ``tau``, with the noise
    ``conditioning`` names (the objective, when not given, is ``make_objective(conditioning)``)."""
    obj = objective or make_objective(conditioning)
    z = latent.float().unsqueeze(0)
    return obj.prepare(z, noise_for(clip_id, z.shape, seed, conditioning), tau_index(tau, obj.num_train_timesteps))


@contextmanager
def capture_blocks(transformer, store: dict):
    """Record every block's output into ``store[block index]`` (B, L, D) while the context is open;
    also the head's inputs: ``store["temb"]`` (the condition embedder's time embedding)."""
    handles = []
    for i, block in enumerate(transformer.blocks):
        handles.append(block.register_forward_hook(lambda m, a, out, i=i: store.__setitem__(i, out.detach())))
    handles.append(transformer.condition_embedder.register_forward_hook(
        lambda m, a, out: store.__setitem__("temb", out[0].detach())))
    try:
        yield store
    finally:
        for h in handles:
            h.remove()


@contextmanager
def capture_block_inputs(transformer, store: dict):
    """Record the arguments block 0 is called with (``store["block_args"]``: (args, kwargs)); every block
    of ``WanTransformer3DModel.forward`` gets the same text states, time projection and rotary
    embedding, so ``resume_from`` can run the remaining blocks from any block's output."""
    def pre(module, args, kwargs):
        store["block_args"] = (tuple(a.detach() if torch.is_tensor(a) else a for a in args), dict(kwargs))

    handle = transformer.blocks[0].register_forward_pre_hook(pre, with_kwargs=True)
    try:
        yield store
    finally:
        handle.remove()


def resume_from(transformer, block: int, hidden: torch.Tensor, block_args, temb: torch.Tensor,
                latent_shape) -> torch.Tensor:
    """The model's output when block ``block`` outputs ``hidden``: blocks ``block``+1.. with the recorded
    arguments, then the head (the same computation as a forward hook on that block; tested)."""
    args, kwargs = block_args
    h = hidden
    for blk in transformer.blocks[block + 1:]:
        h = blk(h, *args[1:], **kwargs)
    return direct_head(transformer, h, temb, latent_shape)


@contextmanager
def intervene_block(transformer, block: int, basis: torch.Tensor, alpha: float):
    """A forward hook replacing block ``block``'s output h by h - alpha (h B) B^T on every token."""
    def hook(module, args, out):
        b = basis.to(device=out.device, dtype=torch.float32)
        h = out.float()
        return (h - alpha * (h @ b) @ b.T).to(out.dtype)

    handle = transformer.blocks[block].register_forward_hook(hook)
    try:
        yield
    finally:
        handle.remove()


def direct_head(transformer, hidden: torch.Tensor, temb: torch.Tensor, latent_shape) -> torch.Tensor:
    """Wan's output stage (time-conditioned norm, projection, unpatchify) applied to a residual state
    ``hidden`` (B, L, D), as ``WanTransformer3DModel.forward`` applies it after the last block;
    returns (B, C, F, H, W)."""
    b, _, f, h, w = latent_shape
    p_t, p_h, p_w = transformer.config.patch_size
    if temb.ndim == 3:
        shift, scale = (transformer.scale_shift_table.unsqueeze(0).to(temb.device) + temb.unsqueeze(2)).chunk(2, dim=2)
        shift, scale = shift.squeeze(2), scale.squeeze(2)
    else:
        shift, scale = (transformer.scale_shift_table.to(temb.device) + temb.unsqueeze(1)).chunk(2, dim=1)
    shift, scale = shift.to(hidden.device), scale.to(hidden.device)
    x = (transformer.norm_out(hidden.float()) * (1 + scale) + shift).type_as(hidden)
    x = transformer.proj_out(x)
    x = x.reshape(b, f // p_t, h // p_h, w // p_w, p_t, p_h, p_w, -1).permute(0, 7, 1, 4, 2, 5, 3, 6)
    return x.flatten(6, 7).flatten(4, 5).flatten(2, 3)


def flow_loss(prediction: torch.Tensor, batch) -> float:
    """Unweighted float32 MSE against the velocity target over temporal slots 1.. (slot 0 excluded)."""
    return float(torch.nn.functional.mse_loss(prediction[:, :, 1:].float(), batch.target[:, :, 1:].to(
        prediction.device)))


def forward(transformer, batch, text: torch.Tensor, device, dtype=torch.float32) -> torch.Tensor:
    return transformer(hidden_states=batch.noisy.to(device=device, dtype=dtype),
                       timestep=batch.timestep_tokens.to(device), encoder_hidden_states=text.to(device=device,
                                                                                                dtype=dtype),
                       return_dict=False)[0]


def token_grid(latent_shape, patch_size) -> tuple[int, int, int]:
    """(slots, rows, columns) of the token grid of a (C, F, h, w) latent."""
    _, f, h, w = latent_shape
    pt, ph, pw = patch_size
    return f // pt, h // ph, w // pw

"""The samplers of ``wan-2.2`` (its option ``sampler``); imported only when a Wan pipeline is configured.

``flow-euler`` (the default) is the sampler of the paper's runs. The authors' release generates with
DiffSynth-Studio 2.0.18 (``WanVideoPipeline`` with its defaults: ``FlowMatchScheduler("Wan")``,
``sigma_shift`` 5.0, 50 steps). Its schedule for n steps and shift s = 5:

    u_i = 1 - i / n,  i = 0 .. n-1        (``linspace(1, 0, n + 1)`` without its last point, float32)
    sigma_i = s u_i / (1 + (s - 1) u_i)   timestep_i = 1000 sigma_i
    x_{i+1} = x_i + (sigma_{i+1} - sigma_i) v_i,   sigma_n = 0      (one Euler step per model call)

diffusers' ``FlowMatchEulerDiscreteScheduler`` (shift 5) takes exactly this when it is handed the grid u
(``set_timesteps(sigmas=u)``: it shifts the grid itself, in float32, and appends sigma_n = 0). The Wan
pipeline asks for ``set_timesteps(num_inference_steps)`` only, for which diffusers spaces the grid
between its training sigmas, already shifted (1 and about 0.005), and shifts it again (the last
sigma of 50 steps is 0.024 instead of 0.093); so
``WanFlowEulerScheduler`` supplies the grid when none is given and leaves everything else, the Euler
step included, to diffusers.

The option ``update_dtype`` (``WanFlowEulerScheduler.update_dtype``): "float32" is diffusers' step
(the sample upcast to float32, x + dt v in float32, the result cast to the model output's dtype, which
is bfloat16 for the bfloat16 pipeline); "bfloat16" is DiffSynth's (``FlowMatchScheduler.step`` on
bfloat16 latents: ``sample + model_output * (sigma_ - sigma)``, so dt v is rounded to bfloat16 and
then the sum; ``diffsynth_euler_step``).

``unipc``: the pipeline's own scheduler, as the model repository ships it (for
Wan-AI/Wan2.2-TI2V-5B-Diffusers ``UniPCMultistepScheduler`` with flow_shift 5.0): what this adapter
used before issue 24.
"""

from __future__ import annotations

import logging

import torch
from diffusers import FlowMatchEulerDiscreteScheduler
from diffusers.schedulers.scheduling_flow_match_euler_discrete import FlowMatchEulerDiscreteSchedulerOutput

from ..errors import UserError

log = logging.getLogger(__name__)

SHIFT = 5.0  # DiffSynth's sigma_shift for Wan (its WanVideoPipeline default, which the release keeps)
NUM_TRAIN_TIMESTEPS = 1000


def wan_grid(steps: int) -> torch.Tensor:
    """(steps,) float32: DiffSynth's unshifted Wan grid, 1, 1 - 1/steps, ..., 1/steps."""
    return torch.linspace(1.0, 0.0, steps + 1, dtype=torch.float32)[:-1]


def diffsynth_euler_step(sample: torch.Tensor, velocity: torch.Tensor, dt: torch.Tensor) -> torch.Tensor:
    """DiffSynth's Euler step on bfloat16 latents, ``sample + velocity * dt``: the product rounded to bfloat16,
    then the sum (each computed in float32 and rounded once, as torch's bfloat16 arithmetic does on either
    device; ``dt`` is the float32 sigma difference)."""
    step = (velocity.to(torch.bfloat16).float() * dt.float()).to(torch.bfloat16)
    return (sample.to(torch.bfloat16).float() + step.float()).to(torch.bfloat16)


class WanFlowEulerScheduler(FlowMatchEulerDiscreteScheduler):
    """diffusers' flow-matching Euler scheduler with DiffSynth's Wan grid as its default sigmas.

    ``replaced``: the scheduler it replaced in a pipeline (restored by ``use_sampler(pipe, "unipc")``);
    ``update_dtype``: "float32" (diffusers' step) or "bfloat16" (``diffsynth_euler_step``)."""

    replaced = None
    update_dtype = "float32"

    def set_timesteps(self, num_inference_steps: int | None = None, device=None, sigmas=None, mu=None,
                      timesteps=None):
        """As diffusers' (timesteps (n,) = 1000 sigmas, sigmas (n + 1,) ending in 0); with only
        ``num_inference_steps`` given, the grid is ``wan_grid(num_inference_steps)``."""
        if sigmas is None and timesteps is None and num_inference_steps is not None:
            sigmas = wan_grid(int(num_inference_steps)).numpy()
        super().set_timesteps(num_inference_steps, device=device, sigmas=sigmas, mu=mu, timesteps=timesteps)

    def step(self, model_output, timestep, sample, *args, **kwargs):
        """diffusers' step, or with ``update_dtype`` "bfloat16" DiffSynth's (bfloat16 latents out)."""
        if self.update_dtype != "bfloat16":
            return super().step(model_output, timestep, sample, *args, **kwargs)
        if self.step_index is None:
            self._init_step_index(timestep)
        dt = self.sigmas[self.step_index + 1] - self.sigmas[self.step_index]
        prev = diffsynth_euler_step(sample, model_output, dt)
        self._step_index += 1
        return FlowMatchEulerDiscreteSchedulerOutput(prev_sample=prev) if kwargs.get("return_dict", True) else (prev,)


def flow_euler_scheduler() -> WanFlowEulerScheduler:
    """A new scheduler of the flow-euler sampler (shift 5.0, 1000 training timesteps)."""
    return WanFlowEulerScheduler(num_train_timesteps=NUM_TRAIN_TIMESTEPS, shift=SHIFT)


def use_sampler(pipe, sampler: str):
    """Give ``pipe`` the scheduler of ``sampler`` (in place); returns that scheduler."""
    current = pipe.scheduler
    if sampler == "flow-euler":
        if not isinstance(current, WanFlowEulerScheduler):
            scheduler = flow_euler_scheduler()
            scheduler.replaced = current
            pipe.register_modules(scheduler=scheduler)
    elif sampler == "unipc":
        if isinstance(current, WanFlowEulerScheduler):
            if current.replaced is None:
                raise UserError("wan-2.2: sampler unipc asks for the pipeline's own scheduler, but this pipeline "
                                "came with the flow-euler one; load the pipeline again or use sampler flow-euler")
            pipe.register_modules(scheduler=current.replaced)
        if type(pipe.scheduler).__name__ != "UniPCMultistepScheduler":
            log.warning("wan-2.2: sampler unipc runs the pipeline's own scheduler, which is a %s here",
                        type(pipe.scheduler).__name__)
    else:
        raise UserError(f"wan-2.2: option sampler must be flow-euler or unipc, got {sampler!r}")  # wan.SAMPLERS
    return pipe.scheduler

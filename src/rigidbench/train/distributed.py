"""Process-group setup for ``train``: one process, or ``torchrun`` (RANK, WORLD_SIZE, LOCAL_RANK set).

NCCL on CUDA, gloo on the CPU. LoRA runs wrap the transformer in DDP; full fine-tuning shards it with
FSDP2 (``fully_shard`` on every transformer block, then on the root), bf16 parameters and float32
gradient reduction on a GPU. One process uses neither wrapper (same arithmetic, nothing to sync).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from datetime import timedelta

import torch
import torch.distributed as dist


@dataclass(frozen=True)
class DistInfo:
    rank: int
    world_size: int
    local_rank: int
    device: torch.device
    backend: str | None  # None: one process, no process group

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        return self.backend is not None


def init_distributed(device: str | None = None) -> DistInfo:
    """Join the torchrun process group when launched by torchrun; pick the device (``device``, else
    CUDA device LOCAL_RANK when available, else the CPU)."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    local = int(os.environ.get("LOCAL_RANK", "0"))
    if device:
        dev = torch.device(device)
    else:
        dev = torch.device("cuda") if torch.cuda.is_available() else torch.device("cpu")
    if dev.type == "cuda":
        dev = torch.device("cuda", local if dev.index is None else dev.index)
        torch.cuda.set_device(dev)
    if world == 1:
        return DistInfo(0, 1, 0, dev, None)
    backend = "nccl" if dev.type == "cuda" else "gloo"
    if not dist.is_initialized():
        dist.init_process_group(backend, timeout=timedelta(minutes=30),
                                device_id=dev if dev.type == "cuda" else None)
    return DistInfo(dist.get_rank(), dist.get_world_size(), local, dev, backend)


def shutdown(info: DistInfo) -> None:
    if info.distributed and dist.is_initialized():
        dist.barrier()
        dist.destroy_process_group()


def barrier(info: DistInfo) -> None:
    if info.distributed:
        dist.barrier()


def mean_across(info: DistInfo, value: float) -> float:
    """The mean of ``value`` over all processes."""
    if not info.distributed:
        return float(value)
    t = torch.tensor([float(value)], dtype=torch.float64,
                     device=info.device if info.backend == "nccl" else "cpu")
    dist.all_reduce(t)
    return float(t.item()) / info.world_size


def broadcast_object(info: DistInfo, obj):
    """``obj`` from rank 0 on every process."""
    if not info.distributed:
        return obj
    box = [obj]
    dist.broadcast_object_list(box, src=0)
    return box[0]


def wrap_ddp(model, info: DistInfo):
    from torch.nn.parallel import DistributedDataParallel

    ids = [info.device.index] if info.device.type == "cuda" else None
    return DistributedDataParallel(model, device_ids=ids, find_unused_parameters=False)


def wrap_fsdp(model, info: DistInfo, bf16: bool, reduce_dtype=torch.float32):
    """FSDP2 full sharding: one unit per transformer block, then the root (the paper's "wrapped by DiT
    block"); bf16 parameters in forward/backward with ``reduce_dtype`` gradient reduction (float32;
    the release's bfloat16 with ``master_weights: bfloat16``) when ``bf16``; the master weights,
    gradients and AdamW state stay sharded."""
    from torch.distributed.fsdp import MixedPrecisionPolicy, fully_shard

    kwargs = {}
    if bf16:
        # inputs keep their dtype: the float32 per-token timesteps must not be rounded to bfloat16 (the
        # pipeline passes them in float32); the forward pass runs under bf16 autocast anyway
        kwargs["mp_policy"] = MixedPrecisionPolicy(param_dtype=torch.bfloat16, reduce_dtype=reduce_dtype,
                                                   cast_forward_inputs=False)
    for block in model.blocks:
        fully_shard(block, **kwargs)
    fully_shard(model, **kwargs)
    return model

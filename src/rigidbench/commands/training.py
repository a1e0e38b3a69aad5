"""The ``preprocess`` and ``train`` commands (fine-tuning Wan 2.2; what they run: ``train.commands``)."""

from __future__ import annotations

from pathlib import Path

from ..argtypes import existing_folder, output_folder, positive_int
from ..train.config import MODEL_SPECS, NAMED_CONFIGS, RESIZES, VAE_DTYPES
from . import Command


def _preprocess_arguments(p) -> None:
    p.add_argument("--data", type=existing_folder, required=True,
                   help="reference bundles: the training split directory (data/train) or a data root")
    p.add_argument("--split", choices=("train", "eval"), default="train",
                   help="split under a data root (default: train)")
    p.add_argument("--out", type=output_folder, required=True,
                   help="cache directory (created; a rerun skips done clips)")
    p.add_argument("--model", choices=tuple(MODEL_SPECS), default="wan-2.2",
                   help="wan-2.2 (640x352, 49 frames; the paper) or tiny (random tiny models, CPU tests)")
    p.add_argument("--model-path", type=Path, help="a local diffusers pipeline directory instead of the hub")
    p.add_argument("--shard-size", type=int, default=64,
                   help="ignored, kept so older scripts run: the cache now keeps one latent file per clip")
    p.add_argument("--resize", choices=RESIZES, default="bicubic",
                   help="frame resize filter: bicubic (PIL's default, the authors' release; default) or lanczos")
    p.add_argument("--vae-dtype", choices=VAE_DTYPES, default="auto",
                   help="VAE precision: auto (bfloat16 on a GPU, as the release; float32 on the CPU)")
    p.add_argument("--device", dest="net_device", help="e.g. cuda or cpu (default: CUDA when available)")
    p.add_argument("--ray-shards", type=positive_int, metavar="N",
                   help="--executor ray: Ray actors encoding clips (default: the cluster's GPUs)")


def _train_arguments(p) -> None:
    p.add_argument("--config", dest="train_config", required=True, metavar="NAME|PATH",
                   help=f"{'|'.join(NAMED_CONFIGS)} (configs/train/NAME.yaml) or a YAML file")
    p.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="override one setting, e.g. --set max_steps=100 --set optimizer.lr=5e-5 (repeatable)")
    p.add_argument("--cache", type=existing_folder, required=True, help="the directory `rigidbench preprocess` wrote")
    p.add_argument("--out", type=output_folder, required=True,
                   help="run directory: metrics.jsonl, checkpoints/step-N; rerunning continues from the last")
    p.add_argument("--device", dest="net_device", help="e.g. cuda or cpu (default: CUDA when available)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


COMMANDS = (
    Command("preprocess", "encode a training split for fine-tuning Wan 2.2: prompts with UMT5, clips with the VAE, "
                          "one file per clip (reruns encode only clips whose inputs or settings changed)",
            "rigidbench.train.commands:cmd_preprocess", _preprocess_arguments,
            groups=("selection", "executor", "progress")),
    Command("train", "fine-tune Wan 2.2 on a preprocessed cache: LoRA (DDP) or full (FSDP); launch with torchrun "
                     "for several GPUs; resumes from RUN",
            "rigidbench.train.commands:cmd_train", _train_arguments),
)

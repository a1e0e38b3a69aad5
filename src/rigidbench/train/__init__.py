"""Fine-tuning Wan 2.2 TI2V-5B on simulator clips (paper, section 5.1 and appendix D).

Two commands, both resumable:

``rigidbench preprocess --data DIR/train --out CACHE [--model wan-2.2|tiny]``
    Wan's UMT5 encodes each distinct prompt once and its VAE encodes each clip (all frames resized
    to 640x352 for Wan 2.2) into float16 shards with a manifest (``cache.py`` documents the layout).

``rigidbench train --config lora|full|tiny|PATH.yaml --cache CACHE --out RUN``
    The flow-matching objective of appendix D (``objective.py``) with LoRA under DDP or full
    fine-tuning under FSDP2 (``trainer.py``); checkpoints loadable by ``predict wan-2.2
    --checkpoint`` next to the resumable training state (``checkpoint.py`` documents the layout).

``tiny.py`` builds randomly initialised Wan models of the real classes, small enough for a CPU;
tests, benchmarks and newcomers use them. Only ``config`` and ``commands`` are light; every other
module imports torch, diffusers or peft at its top and is imported only by the train commands.
"""

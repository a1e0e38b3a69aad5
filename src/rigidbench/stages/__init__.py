"""The stages: one module per stage of the stage driver (``rigidbench.driver``), each holding its ``Stage``, its
``StageWorker`` and the function a command calls. The module is named after the stage.

The data flow, stage by stage (the command that runs it in brackets):

- ``simulate`` [simulate]: manifest rows -> scene specs (``scene_spec``) -> Bullet trajectories and contacts;
- ``render`` [render]: manifest rows -> simulated and rendered bundles in ``DATA/<split>/<id>/``;
- ``import_set`` (stage ``import``) [download, import]: the published evaluation set -> bundles in ``DATA/eval``;
- ``predict`` [predict]: bundles -> one video per example from a model, in ``predictions/MODEL/``;
- ``evaluate`` [evaluate]: predictions and bundles -> the ten measurements, in a run folder (then ``report``,
  ``readouts``);
- ``preprocess`` [preprocess]: training bundles -> a cache of Wan 2.2 latents and prompt encodings (then ``train``);
- ``probe_extract`` (stage ``probe-extract``) [probe extract]: the cache -> an activation store (then ``probe fit``);
- ``probe_bases`` (stage ``probe-bases``) and ``probe_intervene`` (stage ``probe-intervene``) [probe intervene]:
  the store -> INLP bases per block x tau cell, then the loss change on each clip with a basis removed.

A stage module imports the driver and the libraries below it, never another stage module (``probe_intervene``
runs ``probe_bases`` first, its one exception); what runs several stages in a row is in ``flows``. Heavy
packages (bpy, torch) are imported by the modules that need them, so a command imports its stage only when it
runs.
"""

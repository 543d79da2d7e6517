"""Weakly supervised training of LRF-Net (the paper's Siamese Chamfer loss).

  model.py         seeded initial parameters (the weight network, the ablation variants)
  networks.py      its flax.linen modules (layers, initialisation; inference never imports flax)
  losses.py        Chamfer (eq_cham) and the Siamese training loss
  config.py        `TrainConfig`, presets (`configs/NAME.py`), CLI overrides
  batches.py       training keypoints, patches, augmentation, sharded batches
  data_sources.py  the training clouds: BR or the demo
  train_step.py    `TrainState`, Adam and its learning-rate schedule, the jitted step
  checkpoints.py   orbax checkpoints: save, resume, restore_params
  train_lib.py     validation and the training loop (`train_and_evaluate`)
"""

"""Config presets: `python train.py --config NAME` loads `lrf_jax/configs/NAME.py:get_config()`."""

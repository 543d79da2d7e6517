"""Config presets: `python train.py --config NAME` loads `lrf_jax/learning/configs/NAME.py:get_config()`."""

"""JAX's persistent compilation cache for the command-line programs.

A fresh `lrf-register` or `lrf-frames` process would otherwise recompile every jitted function
it calls (seconds per function). `enable()` points JAX's own on-disk cache
(`jax_compilation_cache_dir`) at a per-user directory, so a second run loads the compiled code
instead. The numba kernels of `lrf_jax.engine` have their own cache (`cache=True`).
"""

from __future__ import annotations

import os
from pathlib import Path

import jax

ENV_VAR = "LRF_JAX_CACHE_DIR"


def cache_dir() -> Path:
  """The cache directory: `$LRF_JAX_CACHE_DIR`, else `$XDG_CACHE_HOME/lrf_jax/jax`, else
  `~/.cache/lrf_jax/jax`."""
  explicit = os.environ.get(ENV_VAR)
  if explicit:
    return Path(explicit).expanduser()
  base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
  return Path(base).expanduser() / "lrf_jax" / "jax"


def enable(directory: str | os.PathLike | None = None) -> Path | None:
  """Turn on JAX's persistent compilation cache in `directory` (default: `cache_dir()`).

  Every compiled function is stored, however short its compilation. A directory that cannot be
  created leaves the cache off (the program still runs, only slower to start).

  Returns:
    The directory in use, or None when the cache stays off.
  """
  path = Path(directory).expanduser() if directory is not None else cache_dir()
  try:
    path.mkdir(parents=True, exist_ok=True)
  except OSError:
    return None
  jax.config.update("jax_compilation_cache_dir", str(path))
  jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
  jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
  return path

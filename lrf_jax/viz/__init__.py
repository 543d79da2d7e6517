"""The browser viewer (`lrf-view`, `lrf_jax.view`): scans, models and registrations in 3D, served
by viser (the `viz` extra: `pip install 'lrf_jax[viz]'`).

  api.py       `view`: a Registration, a MultiwayResult, an output folder or two clouds
  scenes.py    what is shown, as data: a model's scans and edges, a pair; thinning for display
  folders.py   the folders of `lrf-register --out-dir` and `lrf-batch register` read back
  draw.py      the page: clouds, legends, toggles, edges, the pair picker
  server.py    viser imported on demand, the address checked, `Viewer` (what `view` returns)

Importing the package imports no viser: `view` imports it when called and names the extra when
it is missing.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
  from lrf_jax.viz.api import view
  from lrf_jax.viz.server import Viewer

__all__ = ["Viewer", "view"]


def __getattr__(name: str) -> Any:
  """The names above, loaded on first use."""
  if name == "view":
    from lrf_jax.viz import api
    return api.view
  if name == "Viewer":
    from lrf_jax.viz import server
    return server.Viewer
  raise AttributeError(f"module 'lrf_jax.viz' has no attribute {name!r}")

"""`view`: a registration, a multiway model, an output folder or two clouds in the browser.

`content_of` reads what is to be shown (every file read and checked before a server starts),
`serve` starts the server and puts it on the page; `view` does both, `lrf-view` too.
"""

from __future__ import annotations

import dataclasses
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from lrf_jax.viz.scenes import (MAX_POINTS, ModelScene, PairScene, model_scene, pair_scene,
                                registration_verdict, thinning_note)
from lrf_jax.viz.server import DEFAULT_HOST, Viewer, address_problem, host_warning

if TYPE_CHECKING:
  from lrf_jax.multiway.result import MultiwayResult
  from lrf_jax.registration.result import Registration
  from lrf_jax.viz.folders import BatchPair

__all__ = ["Content", "content_of", "serve", "view"]


@dataclasses.dataclass(frozen=True)
class Content:
  """What a viewer shows: a model, a pair, or a batch folder's pairs (read when picked)."""
  title: str
  model: ModelScene | None = None
  pair: PairScene | None = None
  pairs: tuple[BatchPair, ...] = ()

  def note(self, max_points: int) -> str | None:
    """The line that says which clouds are thinned for display (None: none is)."""
    scene = self.model or self.pair
    return None if scene is None else thinning_note(scene.thinned, max_points)


def _is_model(what: Any) -> bool:
  return all(hasattr(what, a) for a in ("poses", "edges", "in_model", "names"))


def _is_registration(what: Any) -> bool:
  return all(hasattr(what, a) for a in ("transform", "success", "reason"))


def _transform(transform: Any) -> Any:
  """A transform given as a file (`lrf-register --out`'s 4x4 text) or a matrix."""
  if isinstance(transform, (str, os.PathLike)):
    from lrf_jax.io.poses import read_xf
    return read_xf(transform)
  return transform


def folder_content(folder: str | os.PathLike, *, max_points: int = MAX_POINTS,
                   seed: int = 0) -> Content:
  """An output folder's content (`lrf_jax.viz.folders`).

  Raises:
    ValueError: a folder of neither kind, or a file it holds that cannot be read.
  """
  from lrf_jax.viz import folders
  if folders.folder_kind(folder) == "model":
    model = folders.read_model_folder(folder, max_points=max_points, seed=seed)
    return Content(str(folder), model=model)
  return Content(str(folder), pairs=tuple(folders.read_batch_folder(folder)))


def content_of(what: Any, clouds: tuple[Any, ...] = (), transform: Any = None, *,
               max_points: int = MAX_POINTS, seed: int = 0) -> Content:
  """What `view(what, *clouds, transform=transform)` shows, read and checked.

  Raises:
    ValueError: arguments that do not fit one of `view`'s forms, or a cloud, transform or
      folder that cannot be read. FileNotFoundError: a missing file.
  """
  if not (isinstance(max_points, int) and max_points >= 1):
    raise ValueError(f"max_points: expected a positive integer, got {max_points!r}")
  kw: dict[str, Any] = dict(max_points=max_points, seed=seed)
  if _is_model(what):
    if len(clouds) != 1 or transform is not None:
      raise ValueError("view(model, scans): a MultiwayResult holds poses, not points; pass the "
                       "scans given to register_all as one sequence")
    return Content("register_all's result", model=model_scene(what, clouds[0], **kw))
  if _is_registration(what):
    if len(clouds) != 2 or transform is not None:
      raise ValueError("view(registration, source, target): a Registration holds the "
                       "transform, not the clouds; pass the source and the target")
    t = what.transform if getattr(what, "estimated", True) else None  # else the identity
    return Content("registration", pair=pair_scene(*clouds, t,
                                                   verdict=registration_verdict(what), **kw))
  if isinstance(what, (str, os.PathLike)) and Path(what).expanduser().is_dir():
    if clouds or transform is not None:
      raise ValueError(f"view(folder): {what} is a folder; it takes no clouds nor transform")
    return folder_content(what, **kw)
  if len(clouds) != 1:
    raise ValueError("view: expected a Registration and its two clouds, a MultiwayResult and "
                     "its scans, an output folder, or a source and a target cloud (and "
                     f"transform=); got {1 + len(clouds)} positional arguments")
  return Content("pair", pair=pair_scene(what, clouds[0], _transform(transform), **kw))


def serve(content: Content, *, host: str = DEFAULT_HOST, port: int | None = None,
          open_browser: bool = False, max_points: int = MAX_POINTS, seed: int = 0,
          err: Any = None) -> Viewer:
  """Start a viewer of `content` on `host`:`port` (None: a free port); the warning of a host
  other machines reach and the thinning note are written to `err` (default stderr).

  Raises:
    ValueError: the address cannot be listened on (the message names --host or --port).
    MissingExtraError: viser is not installed.
  """
  from lrf_jax.viz import draw
  from lrf_jax.viz.server import import_viser, start_server
  err = sys.stderr if err is None else err
  import_viser()
  problem = address_problem(host, port)
  if problem:
    raise ValueError(problem)
  warning = host_warning(host)
  if warning:
    print(warning, file=err, flush=True)
  note = content.note(max_points)
  if note:
    print(note, file=err, flush=True)
  try:
    server = start_server(host, port, title=f"lrf_jax: {content.title}")
  except OSError as e:
    raise ValueError(str(e)) from None
  viewer = Viewer(server, host)
  try:
    if content.model is not None:
      draw.show_model(server, content.model, max_points=max_points)
    elif content.pair is not None:
      draw.show_pair(server, content.pair, max_points=max_points)
    else:
      draw.show_batch(server, content.pairs, max_points=max_points, seed=seed,
                      title=content.title, notify=lambda line: print(line, file=err, flush=True))
  except BaseException:
    viewer.stop()
    raise
  if open_browser:
    viewer.open_browser()
  return viewer


def view(what: Registration | MultiwayResult | str | os.PathLike | Any, *clouds: Any,
         transform: Any = None, host: str = DEFAULT_HOST, port: int | None = None,
         open_browser: bool = False, max_points: int = MAX_POINTS, seed: int = 0) -> Viewer:
  """Show a registration, a multiway model, an output folder or two clouds in the browser.

      viewer = lrf_jax.view(reg, source, target)     # reg = lrf_jax.register(source, target)
      viewer = lrf_jax.view(model, scans)            # model = lrf_jax.register_all(scans)
      viewer = lrf_jax.view("model/")                # lrf-register ... --out-dir model/
      viewer = lrf_jax.view("a.ply", "b.ply", transform="T.txt")
      viewer.url                                     # 'http://127.0.0.1:PORT/'
      viewer.stop()

  The server runs in a thread of this process (viser, the `viz` extra), so `view` returns at
  once: in a notebook, the returned `Viewer` as a cell's value shows the page inline; a script
  calls `viewer.wait()` to serve until Ctrl-C. A model shows every scan at its pose in its
  colour (merged.ply's), a legend and a toggle per scan, and the pose graph's edges between the
  scans' centroids (accepted, accepted but "not sure", rejected); a pair shows the target, the
  source moved by the transform and the source before it; a batch folder a picker of its
  pairs. A cloud of more than `max_points` points is shown as a seeded sample of that many (one
  line on stderr says so).

  Args:
    what: a `Registration` (then `clouds` = its source and target: paths, arrays or clouds),
      a `MultiwayResult` (then `clouds` = one sequence, the scans given to `register_all`), an
      output folder (`lrf-register --out-dir`, `lrf-batch register --out`), or a source cloud
      (then `clouds` = the target).
    *clouds: as `what` says.
    transform: with two clouds: a (4, 4) source->target matrix or a file holding one (as
      `lrf-register --out` writes it); None shows the clouds as they are.
    host: the address to listen on; the default serves this machine only. Another one (e.g.
      "0.0.0.0") serves the network, without a password: a warning line says so.
    port: the port; None picks a free one.
    open_browser: open the page in the default web browser.
    max_points: the most points shown per cloud.
    seed: the seed of the thinning sample.

  Returns:
    The running `Viewer`: `.url`, `.server` (the `viser.ViserServer`), `.stop()`, `.wait()`.

  Raises:
    ValueError: arguments that fit none of the forms above, a cloud, transform or folder that
      cannot be read, or an address that cannot be listened on. FileNotFoundError: a missing
      file. MissingExtraError: viser is not installed (`pip install 'lrf_jax[viz]'`).
  """
  from lrf_jax.viz.server import import_viser
  import_viser("lrf_jax.view")  # before any file is read
  content = content_of(what, clouds, transform, max_points=max_points, seed=seed)
  return serve(content, host=host, port=port, open_browser=open_browser,
               max_points=max_points, seed=seed)

"""The work of one item of a data-set job: pure functions of an input file (or two) and options.

Each function takes a payload dict (paths and options: cheap to ship to a worker) and returns a
dict: `status` "done" with the results, or "error" with `error` naming the file and what is wrong
with it; an item's own failure never raises, so one bad scan costs one row, not the job.
"""

from __future__ import annotations

import errno
import os
import time
import warnings
from typing import Any
from collections.abc import Sequence

import numpy as np

__all__ = ["FRAMES_OPTIONS", "check_frames_options", "check_register_options", "frames_of_scan",
           "is_transient", "register_pair"]

# `run_frames` keywords -> lrf-frames flags (the item is lrf-frames' own computation).
FRAMES_OPTIONS = {"keypoints": "--keypoints", "voxel_mr": "--keypoint-voxel-mr",
                  "voxel_size": "--voxel-size", "method": "--method", "weights": "--weights",
                  "radius_mr": "--radius-mr", "viewpoint": "--viewpoint",
                  "descriptor": "--descriptor", "seed": "--seed", "bin_layout": "--bin-layout"}


# OSErrors of the machine, not of an input file: a full, read-only or failing disk, a quota, no
# memory or no process left. The same command redoes an item that met one.
_MACHINE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EIO, errno.ENOMEM,
                             errno.EAGAIN, errno.EMFILE, errno.ENFILE, errno.ESTALE})


def is_transient(e: BaseException, inputs: Sequence[str] = ()) -> bool:
  """Whether `e` is a failure of the machine rather than of the item's inputs: no memory, an
  OSError with a machine's errno, or one about a file that is not an input (a cache, a
  temporary file), and a damaged cache entry (an unpickling error); anywhere in its chain."""
  import pickle
  seen: set[int] = set()
  while e is not None and id(e) not in seen:
    seen.add(id(e))
    if isinstance(e, (MemoryError, pickle.UnpicklingError, EOFError)):
      return True
    if isinstance(e, OSError) and (e.errno in _MACHINE_ERRNOS or (
        e.filename is not None and os.fspath(e.filename) not in inputs
        and not isinstance(e, (FileNotFoundError, IsADirectoryError, NotADirectoryError)))):
      return True
    e = e.__cause__ or e.__context__
  return False


def _error(e: BaseException, t0: float, inputs: Sequence[str] = ()) -> dict[str, Any]:
  """The error record of an item that raised `e`: status "transient" for a failure of the
  machine (`is_transient`; redone by the same command), else "error" (kept until retried).
  Ctrl-C is not an item's error: a KeyboardInterrupt that surfaced as another exception (numba
  turns one inside a kernel into a SystemError) is raised again, so that the job stops and the
  item stays pending."""
  from lrf_jax.io.atomic import caused_by_interrupt
  if caused_by_interrupt(e):
    raise KeyboardInterrupt from e
  text = str(e) if isinstance(e, (ValueError, OSError)) else f"{type(e).__name__}: {e}"
  status = "transient" if is_transient(e, inputs) else "error"
  return dict(status=status, error=text, seconds=time.perf_counter() - t0)


# A registration job's option that is no keyword of `register`: how its items read `.bin`
# sweeps (`lrf_jax.io.read_cloud`'s `bin_layout`, `--bin-layout`).
READ_OPTIONS = ("bin_layout",)


def check_register_options(options: dict[str, Any]) -> None:
  """ValueError unless every key is a keyword of `lrf_jax.register` a job can take, or
  `READ_OPTIONS` (a valid `bin_layout`), and every value is plain data (numbers, strings,
  booleans, None, lists of them)."""
  from lrf_jax.io.sweeps import check_bin_layout
  from lrf_jax.registration.options import FIELDS
  known = [*FIELDS, *READ_OPTIONS]
  check_bin_layout(options.get("bin_layout"))
  for key, value in options.items():
    if key not in known:
      raise ValueError(f"{key}: not an option of a registration job; expected one of "
                       f"{sorted(known)}")
    if not _plain(value):
      raise ValueError(f"{key}: expected a number, string, boolean, None or a list of them, "
                       f"got {type(value).__name__}")


def _plain(value: Any) -> bool:
  if isinstance(value, (list, tuple)):
    return all(_plain(v) for v in value)
  return value is None or isinstance(value, (bool, int, float, str))


def register_pair(payload: dict[str, Any]) -> dict[str, Any]:
  """`lrf_jax.register(source, target, **options)` of one pair.

  Args:
    payload: {"source": path, "target": path, "options": register's keywords, and optionally
      `bin_layout`, how a `.bin` input is read (`lrf_jax.io.reader.cloud_source`); "init": a
      4 x 4 transform file (as `lrf-register --init` reads it; a rotation block within
      `refine.INIT_PROJECT` of orthonormal projected) or None}.

  Returns:
    {"status": "done", "transform": 4 x 4 nested lists (float64, exact), "success": bool,
    "reason": str, "seconds": float} or {"status": "error", "error": str, "seconds": float}.
  """
  t0 = time.perf_counter()
  try:
    from lrf_jax.io.reader import cloud_source
    from lrf_jax.registration import register
    options = dict(payload["options"])
    layout = options.pop("bin_layout", None)
    if payload.get("init"):
      from lrf_jax.batch.scan_frames import read_transform
      from lrf_jax.registration.refine import INIT_PROJECT
      try:
        with warnings.catch_warnings():
          warnings.simplefilter("ignore")  # the projection's note: the row's reason says enough
          options["init"] = read_transform(payload["init"], "init", project=INIT_PROJECT)
      except (FileNotFoundError, IsADirectoryError, NotADirectoryError) as e:
        raise ValueError(f"init: {e}") from None  # the item's input, named by its column
    reg = register(cloud_source(payload["source"], layout),
                   cloud_source(payload["target"], layout), **options)
  except Exception as e:  # noqa: BLE001 -- a bad pair is a row, the job goes on
    return _error(e, t0, (payload["source"], payload["target"])
                  + ((payload["init"],) if payload.get("init") else ()))
  return dict(status="done", transform=np.asarray(reg.transform, np.float64).tolist(),
              success=bool(reg.success), reason=str(reg.reason),
              seconds=time.perf_counter() - t0)


def _finite_point(value: Any) -> bool:
  """Whether `value` is a list or tuple of three finite real numbers (lrf-frames checks a
  viewpoint only when it reads the cloud: a job checks it before its first item)."""
  if not isinstance(value, (list, tuple)) or len(value) != 3:
    return False
  return all(isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v)
             for v in value)


def check_frames_options(options: dict[str, Any]) -> None:
  """ValueError unless `options` are lrf-frames options (`FRAMES_OPTIONS`) it accepts."""
  for key, value in options.items():
    if key not in FRAMES_OPTIONS:
      raise ValueError(f"{key}: not an option of a frames job; expected one of "
                       f"{sorted(FRAMES_OPTIONS)}")
    if key == "viewpoint" and not _finite_point(value):
      raise ValueError(f"viewpoint: expected three finite numbers (the sensor's position), got "
                       f"{value!r}")
    if not _plain(value):
      raise ValueError(f"{key}: expected a number or a string, got {type(value).__name__}")
  try:
    request = _request("scan", options)
  except (TypeError, ValueError):
    raise ValueError(f"frames options: lrf-frames refuses {options}") from None
  problem = request.problem()
  if problem:
    raise ValueError(problem)


def _request(scan: str, options: dict[str, Any]) -> Any:
  """The `FrameOptions` of a scan and a frames job's options (values as lrf-frames' flags
  read them: a count of keypoints as text, numbers as numbers)."""
  from lrf_jax.batch.scan_frames import FrameOptions
  kw = dict(options)
  if kw.get("keypoints") is not None:
    kw["keypoints"] = str(kw["keypoints"])
  for key, kind in (("voxel_mr", float), ("voxel_size", float), ("radius_mr", float),
                    ("seed", int)):
    if kw.get(key) is not None:
      kw[key] = kind(kw[key])
  if kw.get("viewpoint") is not None:
    kw["viewpoint"] = tuple(float(v) for v in kw["viewpoint"])
  return FrameOptions(cloud=scan, **kw)


def frames_of_scan(payload: dict[str, Any]) -> dict[str, Any]:
  """lrf-frames' computation for one scan (`lrf_jax.batch.scan_frames.frames_of_scan`).

  Args:
    payload: {"scan": path, "options": `FRAMES_OPTIONS` keywords}.

  Returns:
    {"status": "done", "arrays": the .npz fields lrf-frames writes, "keypoints": int,
    "valid": int, "seconds": float} or {"status": "error", "error": str, "seconds": float}.
  """
  t0 = time.perf_counter()
  try:
    from lrf_jax.batch import scan_frames
    arrays, _, _ = scan_frames.frames_of_scan(_request(payload["scan"], payload["options"]))
  except Exception as e:  # noqa: BLE001 -- a bad scan is a row, the job goes on
    return _error(e, t0, (payload["scan"],))
  arrays = {k: np.asarray(v) for k, v in arrays.items()}
  return dict(status="done", arrays=arrays, keypoints=int(len(arrays["keypoints"])),
              valid=int(arrays["valid"].sum()), seconds=time.perf_counter() - t0)

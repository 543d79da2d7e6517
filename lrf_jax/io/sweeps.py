"""LiDAR sweeps in raw `.bin` files: float32 records of 16 bytes (x, y, z, reflectance: KITTI's
Velodyne layout, the default) or of 12 bytes (x, y, z), in the sensor's frame (metres).

A `.bin` file holds no header, so only its size and its values tell the layouts apart:

* a size that is a whole number of one layout's records only is read in that layout when that
  layout is asked for (or none is and it is the default's) and refused otherwise, naming both
  layouts and `bin_layout` (`--bin-layout` on the command lines);
* a size that fits both (a multiple of 48 bytes: a quarter of the 12-byte files, a third of the
  16-byte ones) is read in the layout asked for; with none asked for, in the default layout,
  and then checked (`PLAUSIBLE_*`): the 4th column must look like a reflectance (at most 1% of
  its values negative, none beyond 65535 or not finite) and every coordinate must lie within
  `MAX_SWEEP_RANGE` of the sensor. A 12-byte file read as 16-byte records puts coordinates into
  that column: a sensor-frame sweep has points on every side of the sensor, so about half of
  them are negative (62% in KITTI's sweeps; a genuine reflectance, KITTI's [0, 1] or a sensor's
  8- or 16-bit count, is never negative). What the check cannot tell: a cloud lying wholly in
  x, y, z >= 0 (not a sensor-frame sweep); pass the layout explicitly for it.
"""

from __future__ import annotations

import os

import numpy as np

from lrf_jax.io.cloud import Cloud
from lrf_jax.io.validation import bad_input, check_points, require_file

# bin_layout -> (bytes per point, float32 columns, description).
BIN_LAYOUTS = {"xyzi": (16, 4, "float32 x, y, z, reflectance"), "xyz": (12, 3, "float32 x, y, z")}
DEFAULT_BIN_LAYOUT = "xyzi"
# A reflectance column with more than this fraction of negative values is coordinates.
PLAUSIBLE_NEGATIVE_FRACTION = 0.01
# The largest reflectance a sensor writes: a 16-bit count (KITTI's are in [0, 1], many sensors'
# are 8-bit counts, 0-255).
PLAUSIBLE_MAX_REFLECTANCE = 65535.0
# No LiDAR measures beyond this (metres; long-range terrestrial scanners reach a few km).
MAX_SWEEP_RANGE = 1e4


def check_bin_layout(bin_layout: str | None, name: str = "bin_layout") -> str | None:
  """`bin_layout` itself when it is None or a key of `BIN_LAYOUTS`.

  Raises:
    ValueError: any other value, naming `name` and the layouts.
  """
  if bin_layout is not None and bin_layout not in BIN_LAYOUTS:
    raise ValueError(f"{name}: expected one of {', '.join(map(repr, BIN_LAYOUTS))} (16 bytes a "
                     f"point: {BIN_LAYOUTS['xyzi'][2]}, the default; 12 bytes a point: "
                     f"{BIN_LAYOUTS['xyz'][2]}) or None, got {bin_layout!r}")
  return bin_layout


def _layout_text(layout: str) -> str:
  size, _, what = BIN_LAYOUTS[layout]
  default = ", the default" if layout == DEFAULT_BIN_LAYOUT else ""
  return f"{size}-byte points ({what}; bin_layout={layout!r}{default})"


def _option(layout: str) -> str:
  return f"bin_layout={layout!r} (--bin-layout {layout} on the command line)"


def read_kitti_bin(path: str | os.PathLike, *, bin_layout: str | None = None) -> Cloud:
  """Reads a raw LiDAR sweep `.bin`: float32 records of 16 bytes (x, y, z, reflectance; KITTI's
  Velodyne layout, the default) or of 12 bytes (x, y, z), in the sensor's frame (metres; the
  sensor at the origin). The reflectance is dropped (a `Cloud` holds no per-point values).

  Args:
    path: the `.bin` file.
    bin_layout: "xyzi" (16 bytes a point), "xyz" (12 bytes a point) or None: the default
      layout ("xyzi"), with a size that also fits 12-byte points checked for plausibility
      (module docstring; pass "xyzi" to read such a file without the check).

  Returns:
    A Cloud with float64 points (n, 3).

  Raises:
    FileNotFoundError: missing file.
    ValueError: a bad `bin_layout`; a size that is not a whole number of the layout's points
      (naming both layouts and the option when it fits the other one); with no layout given
      and a size that fits both, a 4th column that is not a reflectance or coordinates beyond
      `MAX_SWEEP_RANGE`; empty, or non-finite coordinates.
  """
  check_bin_layout(bin_layout)
  p = require_file(path)
  layout = bin_layout or DEFAULT_BIN_LAYOUT
  other = "xyz" if layout == "xyzi" else "xyzi"
  size = p.stat().st_size
  record, columns, _ = BIN_LAYOUTS[layout]
  fits_other = size > 0 and size % BIN_LAYOUTS[other][0] == 0
  if size == 0 or size % record:
    found = f"{size} bytes"
    if fits_other:
      found += (f": a whole number of {_layout_text(other)}; if the file holds those, pass "
                f"{_option(other)}")
    else:
      found += f", a whole number of neither {_layout_text(layout)} nor {_layout_text(other)}"
    raise bad_input(p, "size", f"a whole number of {_layout_text(layout)}", found)
  arr = np.fromfile(p, dtype="<f4").reshape(-1, columns)
  if bin_layout is None and fits_other:  # either layout: the values decide
    _check_plausible(p, arr, size)
  points = check_points(arr[:, :3].astype(np.float64), p, "x/y/z")
  return Cloud(points, None, None, p)


def _check_plausible(p: object, arr: np.ndarray, size: int) -> None:
  """Raises unless `arr` (n, 4), read as 16-byte points from a file whose size also fits 12-byte
  ones, holds a reflectance in its 4th column and coordinates within `MAX_SWEEP_RANGE`."""
  refl = arr[:, 3]
  both = (f"the file's size ({size} bytes) fits both {_layout_text('xyzi')} and "
          f"{_layout_text('xyz')}: pass {_option('xyz')} if it holds 12-byte points, or "
          f"{_option('xyzi')} to read it as 16-byte points without this check")
  finite = np.isfinite(refl)
  negative = float(np.mean(refl < 0))
  if not finite.all() or negative > PLAUSIBLE_NEGATIVE_FRACTION or (
      refl[finite].max(initial=0.0) > PLAUSIBLE_MAX_REFLECTANCE):
    found = (f"{negative:.0%} negative values, range [{np.nanmin(refl):.4g}, "
             f"{np.nanmax(refl):.4g}]" if finite.any() else "no finite value")
    if not finite.all() and finite.any():
      found += f", {int((~finite).sum())} not finite"
    raise bad_input(p, "reflectance (4th float of each 16-byte point)",
                    f"a reflectance (at most {PLAUSIBLE_NEGATIVE_FRACTION:.0%} negative, finite, "
                    f"at most {PLAUSIBLE_MAX_REFLECTANCE:g})", f"{found} (coordinates?): {both}")
  xyz = arr[:, :3]
  with np.errstate(invalid="ignore"):
    far = np.abs(xyz) > MAX_SWEEP_RANGE
  if far.any():
    raise bad_input(p, "x/y/z", f"a sensor-frame sweep's coordinates, within "
                    f"{MAX_SWEEP_RANGE:g} m of the sensor", f"{int(far.any(axis=1).sum())} "
                    f"points beyond it (largest {float(np.nanmax(np.abs(xyz))):.4g}): {both}")

"""Reusable assertions and fixtures-as-functions for LRF tests (e3nn-jax style helpers): frames,
synthetic meshes, a Ray instance of one's own, the programs' error lines and failed writes,
synthetic pose graphs, and the fuzz oracle with the mutations the file formats share."""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import os
import re
import secrets
import signal
import time
import tracemalloc
import traceback
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import lrf_jax
from lrf_jax import io

REPO = Path(__file__).resolve().parents[1]


def random_rotation(seed: int) -> np.ndarray:
  """A uniformly random (3, 3) rotation, seeded."""
  return Rotation.random(random_state=seed).as_matrix()


def assert_frames_orthonormal(frames, valid=None, atol=1e-5):
  """Rows orthonormal and det = +1 for every frame (invalid frames must be the identity)."""
  f = np.asarray(frames, np.float64)
  eye = np.broadcast_to(np.eye(3), f.shape)
  np.testing.assert_allclose(f @ np.swapaxes(f, -1, -2), eye, atol=atol)
  np.testing.assert_allclose(np.linalg.det(f), 1.0, atol=atol)
  assert np.isfinite(f).all()
  if valid is not None:
    v = np.asarray(valid)
    np.testing.assert_array_equal(f[~v], eye[~v])


def equivariance_deficit(frames, frames_moved, rotation, valid=None, valid_moved=None,
                         up_to_sign=False) -> np.ndarray:
  """Per-keypoint 1 - MeanCos between lrf(P)·Rᵀ and lrf(R·P + t) (0 for a perfect match).

  With `up_to_sign`, cosines are taken in absolute value (for methods whose axis signs are
  ambiguous by definition, e.g. Mian's).
  """
  f = np.asarray(frames, np.float64) @ np.asarray(rotation).T
  g = np.asarray(frames_moved, np.float64)
  cx = np.sum(f[:, 0] * g[:, 0], -1)
  cz = np.sum(f[:, 2] * g[:, 2], -1)
  if up_to_sign:
    cx, cz = np.abs(cx), np.abs(cz)
  mc = 0.5 * (cx + cz)
  if valid is not None:
    mc = np.where(np.asarray(valid) & np.asarray(valid_moved), mc, 0.0)
  return 1.0 - mc


def load_br_model(root: Path, name: str, scene: int | None = None):
  """A BR model as (points (n, 3) float64, faces (f, 3), mr, xf (4, 4) or None), with plyfile."""
  from plyfile import PlyData

  folder = Path(root) / "bologna_retrieval" / "models" / name
  ply = PlyData.read(next(folder.glob("*.ply")))
  v = ply["vertex"]
  pts = np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float64)
  faces = np.stack(ply["face"]["vertex_indices"]).astype(np.int64)
  e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
  e = np.unique(np.sort(e, axis=1), axis=0)
  mr = float(np.linalg.norm(pts[e[:, 0]] - pts[e[:, 1]], axis=1).mean())
  xf = None
  if scene is not None:
    xf = np.loadtxt(Path(root) / "bologna_retrieval" / "scenes" / f"Scene{scene}-rs0.xf")
  return pts, faces, mr, xf


N_GOOD = 12  # interior keypoints of `synthetic_mesh`
GRID = 41  # the height field's grid: GRID x GRID points, spacing 1 (about 1 mr)


def _grid(rng: np.random.Generator, height=None) -> tuple[np.ndarray, np.ndarray]:
  """A GRID x GRID grid of spacing 1 jittered by up to 0.1 in x and y, z = height(x, y) (0
  when None), and its triangles: ((GRID**2, 3) points, (f, 3) faces), row-major (x index
  first)."""
  n = GRID
  gx, gy = np.meshgrid(np.arange(n, dtype=float), np.arange(n, dtype=float), indexing="ij")
  x = gx + rng.uniform(-0.1, 0.1, gx.shape)
  y = gy + rng.uniform(-0.1, 0.1, gy.shape)
  z = np.zeros_like(x) if height is None else height(x, y)
  ids = np.arange(n * n).reshape(n, n)
  a, b, c, d = ids[:-1, :-1], ids[1:, :-1], ids[1:, 1:], ids[:-1, 1:]
  faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3),
                          np.stack([a, c, d], -1).reshape(-1, 3)])
  return np.stack([x, y, z], -1).reshape(-1, 3), faces


def _height(x, y):
  """`synthetic_mesh`'s irregular height field (a few units of relief over the 41 x 41 grid)."""
  return 1.5 * np.sin(0.35 * x + 0.2 * y) + 0.8 * np.cos(0.3 * y - 0.15 * x) + 0.01 * x * y


def _grid_keypoints(rows, cols) -> np.ndarray:
  """Indices of the grid points at (rows x cols), row-major."""
  return np.arange(GRID * GRID).reshape(GRID, GRID)[np.ix_(rows, cols)].reshape(-1)


def _with_degenerate_parts(surface: np.ndarray, faces: np.ndarray, keypoints: np.ndarray):
  """`surface` plus, far away, a pair of points (a keypoint with one neighbor) and 30 collinear
  points with zero-area triangles (a keypoint on a collinear support): (points, faces int64,
  keypoints = `keypoints` then those two, radius 6)."""
  s = len(surface)
  pair = np.array([[500.0, 500.0, 500.0], [500.1, 500.0, 500.0]])  # too few neighbors
  direction = np.array([1.0, 2.0, 3.0]) / np.sqrt(14.0)
  line = np.array([-500.0, -500.0, -500.0]) + 0.5 * np.arange(30)[:, None] * direction  # collinear
  points = np.concatenate([surface, pair, line])
  l0 = s + 2
  line_faces = np.stack([l0 + np.arange(28), l0 + np.arange(1, 29), l0 + np.arange(2, 30)], -1)
  faces = np.concatenate([faces, line_faces])  # zero-area triangles along the line
  return points, faces.astype(np.int64), np.concatenate([keypoints, [s], [l0 + 15]]), 6.0


def synthetic_mesh():
  """An irregular 41 x 41 height field (radius 6) plus two degenerate far-away parts.

  Returns:
    (points, faces, keypoints, radius): the first `N_GOOD` keypoints are interior surface points,
    then a keypoint with one neighbor and one on a collinear support.
  """
  grid, faces = _grid(np.random.default_rng(3), _height)
  interior = _grid_keypoints(range(14, 27, 4), range(14, 27, 4))[:N_GOOD]
  return _with_degenerate_parts(grid, faces, interior)


# The kinds of `host_check_cloud`: every host kernel must give its jitted function's frames on
# each. "tilted_plane" is where some methods' frames are set by float rounding (see there).
HOST_CHECK_KINDS = ("smooth", "noisy", "planar", "cut", "tilted_plane")


def host_check_cloud(kind: str):
  """A procedural mesh of `kind` on which a method's host kernel and its jitted function must
  give the same frames: (points (n, 3) float64, faces (f, 3) int64, keypoints (14,), radius 6).

  The surface is a 41 x 41 grid (spacing 1, about 1 mr; the radius is 6 mr), its 12 keypoints
  first, then `synthetic_mesh`'s two degenerate keypoints (one neighbor; a collinear support),
  which every method must flag invalid:

  * "smooth": `synthetic_mesh` (an irregular height field, all 12 keypoints interior);
  * "noisy": that field with Gaussian noise of 0.1 grid spacings (about 0.1 mr) per axis;
  * "planar": the grid on the exact plane z = 0 (offsets exact in float32 and float64: a frame
    undefined there is invalid on both paths, e.g. TOLDI's x weights h = 0);
  * "cut": the field cut off at x = 20.5, as a scan ends: 4 keypoints on the cut, 8 within 3 mr
    of it (their balls half-empty);
  * "tilted_plane": the "planar" grid rotated: the points' heights above their plane, exactly 0,
    are float rounding (about 1e-7 r in float32, 1e-16 r in float64), so a method that reads
    their signs (a z vote, a highest point, an x weighted by h) may take any frame, and the two
    paths differ.
  """
  from lrf_jax.datasets.nuisances import add_gaussian_noise
  if kind not in HOST_CHECK_KINDS:
    raise ValueError(f"kind: expected one of {HOST_CHECK_KINDS}, got {kind!r}")
  if kind == "smooth":
    return synthetic_mesh()
  rng = np.random.default_rng(5)
  interior = _grid_keypoints(range(14, 27, 4), range(14, 27, 4))[:N_GOOD]
  if kind == "noisy":
    grid, faces = _grid(rng, _height)
    return _with_degenerate_parts(add_gaussian_noise(grid, 0.1, 1.0, rng), faces, interior)
  if kind in ("planar", "tilted_plane"):
    grid, faces = _grid(rng)
    if kind == "tilted_plane":
      grid = grid @ Rotation.from_euler("xyz", [20, 35, 10], degrees=True).as_matrix().T
    return _with_degenerate_parts(grid, faces, interior)
  grid, faces = _grid(rng, _height)
  keep = grid[:, 0] <= 20.5  # rows 0..20 (x = row +- 0.1)
  remap = np.cumsum(keep) - 1
  kp = remap[_grid_keypoints([20, 19, 17], [5, 15, 25, 35])]
  return _with_degenerate_parts(grid[keep], remap[faces[keep[faces].all(1)]], kp)


@contextlib.contextmanager
def own_ray_instance(num_cpus: int = 2) -> Iterator[None]:
  """A Ray instance of the caller's own: new (address "local": never a cluster found on the
  machine or in RAY_ADDRESS), on 127.0.0.1, with a token of its own (nothing read from or
  written to ~/.ray); the environment restored when it ends."""
  import ray
  os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")
  os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")  # no usage report to any address
  from ray._private import ray_constants
  ray_constants.ENABLE_RAY_CLUSTER = False  # the driver stays on loopback
  auth = {k: os.environ.get(k) for k in ("RAY_AUTH_MODE", "RAY_AUTH_TOKEN")}
  os.environ["RAY_AUTH_TOKEN"] = secrets.token_hex(32)  # ray.init turns token mode on
  try:
    ray.init(address="local", num_cpus=num_cpus, include_dashboard=False,
             _node_ip_address="127.0.0.1", logging_level="warning", log_to_driver=False)
    yield
  finally:
    ray.shutdown()
    for k, v in auth.items():
      if v is None:
        os.environ.pop(k, None)
      else:
        os.environ[k] = v
    from ray._raylet import AuthenticationTokenLoader, Config
    Config.initialize("")  # Ray's settings read the restored environment again
    AuthenticationTokenLoader.instance().reset_cache()  # the next instance reads its own token


def repo_env() -> dict[str, str]:
  """This environment with the repository on PYTHONPATH, for a child Python process."""
  return {**os.environ, "PYTHONPATH": str(REPO)}


def unit_sphere(n: int = 600, seed: int = 0) -> np.ndarray:
  """n seeded random points on the unit sphere, (n, 3) float64."""
  pts = np.random.default_rng(seed).normal(size=(n, 3))
  return pts / np.linalg.norm(pts, axis=1, keepdims=True)


def tetrahedron() -> tuple[np.ndarray, np.ndarray]:
  """The unit corner tetrahedron: (points (4, 3) float64, faces (4, 3) wound outwards)."""
  pts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=np.float64)
  faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
  return pts, faces


# ---------------------------------------------------------------------------------------------
# The command-line programs and their writes


def cli_error(capsys) -> str:
  """What a program wrote to stderr: an `error: ` line, no traceback."""
  err = capsys.readouterr().err
  assert err.startswith("error: ") and "Traceback" not in err, err
  return err


ENOSPC = OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def assert_only_files(folder: Path, *names: str) -> None:
  """`folder` holds exactly `names`: no temporary file was left."""
  assert sorted(p.name for p in folder.iterdir()) == sorted(names)


def full_disk_midway(f, *args, **kwargs):
  """A writer that gets half-way and then finds the disk full."""
  f.write(b"partial data")
  raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


# ---------------------------------------------------------------------------------------------
# Pose graphs (lrf_jax.multiway.pose_graph)


def random_poses(n: int, seed: int) -> np.ndarray:
  """(n, 4, 4) seeded rigid poses, the first the identity."""
  rng = np.random.default_rng(seed)
  x = np.tile(np.eye(4), (n, 1, 1))
  x[1:, :3, :3] = Rotation.random(n - 1, random_state=seed).as_matrix()
  x[1:, :3, 3] = rng.normal(size=(n - 1, 3))
  return x


def pose_edges(x: np.ndarray, pairs, seed: int, noise: float = 0.0) -> list:
  """`pose_graph.PoseEdge`s i -> j consistent with poses x (16 random points each), each
  transform perturbed by a random motion of `noise` (radians and units) when given."""
  from lrf_jax.multiway import pose_graph
  rng = np.random.default_rng(seed)
  out = []
  for i, j in pairs:
    t = np.linalg.inv(x[j]) @ x[i]
    if noise:
      d = np.eye(4)
      d[:3, :3] = Rotation.from_rotvec(rng.normal(0, noise, 3)).as_matrix()
      d[:3, 3] = rng.normal(0, noise, 3)
      t = d @ t
    out.append(pose_graph.PoseEdge(i, j, t, rng.normal(size=(16, 3)), 1.0))
  return out


def wrong_edge(e):
  """`e` with its transform moved far off (and the heaviest weight: the first tree takes it)."""
  from lrf_jax.multiway import pose_graph
  bad = np.eye(4)
  bad[:3, :3] = Rotation.from_rotvec([0.3, -1.2, 0.8]).as_matrix()
  bad[:3, 3] = [0.7, 0.1, -0.4]
  return pose_graph.PoseEdge(e.i, e.j, bad @ e.transform, e.points, 1e3)  # heaviest: tree 0


def random_pose(seed: int) -> np.ndarray:
  """One seeded rigid (4, 4) pose."""
  x = np.eye(4)
  x[:3, :3] = Rotation.random(random_state=seed).as_matrix()
  x[:3, 3] = np.random.default_rng(seed).normal(size=3)
  return x


def world_poses(n: int) -> np.ndarray:
  """(n, 4, 4): the identity, then `random_pose(k)` for k = 1 .. n-1."""
  return np.stack([np.eye(4)] + [random_pose(k) for k in range(1, n)])


def edge_between(x, i, j, seed, wrong=None):
  """Edge i -> j from poses x (or from the wrong pose `wrong` of scan i)."""
  from lrf_jax.multiway import pose_graph
  xi = x[i] if wrong is None else wrong
  pts = np.random.default_rng(seed).normal(size=(16, 3))
  return pose_graph.PoseEdge(i, j, np.linalg.inv(x[j]) @ xi, pts, 1.0)


# ---------------------------------------------------------------------------------------------
# The fuzz oracle (tests/test_io_fuzz.py, and the argument fuzz of compute_frames and register in
# tests/test_compute_inputs.py and tests/test_registration.py): seeded cases, each judged by
# `judge`; the byte- and line-level mutations the file formats share.

FUZZ_SEED = 20240607
FUZZ_CASES = {"ply": 200, "pcd": 200, "xyz": 100, "npy": 100, "pose": 100, "compute_frames": 60,
         "register": 16}
FUZZ_TOTAL_CASES = sum(FUZZ_CASES.values())  # 776, as tests/test_io_fuzz.py's docstring states
CASE_SECONDS = 30.0  # per case (the first valid compute_frames/register call compiles)
MAX_TRACED_BYTES = 64 << 20  # Python/numpy allocations while reading one small file
HUGE = ("1000000000000", "4294967296", "4611686018427387904", "9223372036854775807",
        "18446744073709551616")
BAD_NUMBERS = ("nan", "inf", "-inf", "1e999", "abc", "0x10", "1,5", "--1", "9" * 400, "\x00")
LRF_DIR = str(Path(lrf_jax.__file__).parent)


# ---------------------------------------------------------------------------------------------
# The oracle


@dataclasses.dataclass
class Case:
  """One fuzz case: a call, what its error message must name and how to judge a result.

  Attributes:
    label: what was done, for the failure report.
    call: the call under test.
    name: a string every error message must contain (the file's path or the argument's name).
    check: validates a returned result (raises AssertionError when it is not valid).
    outcome: "error" (must raise), "result" (must return) or "either".
    file: True for a reader case (its allocations are bounded).
  """

  label: str
  call: Callable[[], Any]
  name: str
  check: Callable[[Any], None]
  outcome: str = "either"
  file: bool = True


class _Hang(BaseException):
  """Raised by the alarm: a BaseException, so that no `except Exception` swallows it."""


def _on_alarm(signum: int, frame: Any) -> None:
  raise _Hang()


def _raised_in_lrf_jax(e: BaseException) -> bool:
  frames = traceback.extract_tb(e.__traceback__)
  return bool(frames) and frames[-1].filename.startswith(LRF_DIR)


def judge(case: Case) -> str | None:
  """Runs one case under a timeout (and, for files, an allocation bound); None when it passes,
  else what went wrong. A timer already set (pytest-timeout's) and tracing already on are kept."""
  result: Any = None
  error: BaseException | None = None
  tracing = tracemalloc.is_tracing()
  if case.file and tracing:
    tracemalloc.reset_peak()
  elif case.file:
    tracemalloc.start()
  base = tracemalloc.get_traced_memory()[0] if case.file else 0
  old_handler = signal.signal(signal.SIGALRM, _on_alarm)
  t0 = time.perf_counter()
  old_delay, old_interval = signal.setitimer(signal.ITIMER_REAL, CASE_SECONDS)
  try:
    with warnings.catch_warnings():
      warnings.simplefilter("ignore")
      result = case.call()
  except _Hang:
    error = _Hang()
  except Exception as e:  # noqa: BLE001 -- judged below
    error = e
  finally:
    signal.setitimer(signal.ITIMER_REAL, 0)
    signal.signal(signal.SIGALRM, old_handler)
    seconds = time.perf_counter() - t0
    if old_delay > 0:
      signal.setitimer(signal.ITIMER_REAL, max(old_delay - seconds, 1e-3), old_interval)
    peak = tracemalloc.get_traced_memory()[1] - base if case.file else 0
    if case.file and not tracing:
      tracemalloc.stop()
  if isinstance(error, _Hang):
    return f"no answer within {CASE_SECONDS:g} s"
  if seconds > CASE_SECONDS:
    return f"took {seconds:.1f} s"
  if peak > MAX_TRACED_BYTES:
    return f"allocated {peak / 2**20:.0f} MiB (counts must be checked before allocating)"
  if error is not None:
    where = traceback.extract_tb(error.__traceback__)[-1]
    desc = f"{type(error).__name__} at {Path(where.filename).name}:{where.lineno}: {error}"
    if not isinstance(error, (ValueError, FileNotFoundError)):
      return f"wrong exception type: {desc}"
    if not _raised_in_lrf_jax(error):
      return f"raised inside a dependency: {desc}"
    if case.name not in str(error):
      return f"message does not name {case.name!r}: {desc}"
    if case.outcome == "result":
      return f"rejected a valid input: {desc}"
    return None
  if case.outcome == "error":
    return f"returned a result for an input that must be rejected: {short_repr(result)}"
  try:
    case.check(result)
  except (AssertionError, ValueError) as e:  # ValueError: io.check_rigid
    return f"invalid result: {e}"
  return None


def short_repr(x: Any) -> str:
  return repr(x)[:200]


def run_cases(cases: list[Case], expected: int) -> None:
  """Judges every case and fails with a report of the failing ones."""
  assert len(cases) == expected, (len(cases), expected)
  failures = [(c.label, why) for c in cases if (why := judge(c)) is not None]
  report = "\n".join(f"  {label}: {why}" for label, why in failures[:25])
  assert not failures, f"{len(failures)} of {len(cases)} cases failed:\n{report}"


# ---------------------------------------------------------------------------------------------
# Result validators


def _check_points(a: Any, what: str = "points") -> int:
  assert isinstance(a, np.ndarray), f"{what} is {type(a)}"
  assert a.dtype == np.float64 and a.ndim == 2 and a.shape[1] == 3 and len(a), \
      f"{what}: {a.dtype} {a.shape}"
  assert np.isfinite(a).all(), f"{what}: non-finite"
  return len(a)


def check_cloud(c: Any) -> None:
  """A `Cloud` or `PlyMesh`: (n, 3) finite float64 points, optional normals and faces."""
  assert isinstance(c, (io.Cloud, io.PlyMesh)), type(c)
  n = _check_points(c.points)
  if c.normals is not None:  # a normal the file does not give finitely is a NaN row (invalid)
    nrm = c.normals
    assert isinstance(nrm, np.ndarray) and nrm.dtype == np.float64 and nrm.shape == (n, 3), \
        f"normals: {nrm.dtype} {nrm.shape}"
    fin = np.isfinite(nrm)
    assert np.all(fin.all(axis=1) | np.isnan(nrm).all(axis=1)), "normals: a partly finite row"
  if c.faces is not None:
    f = c.faces
    assert f.dtype == np.int64 and f.ndim == 2 and f.shape[1] == 3, (f.dtype, f.shape)
    assert f.size == 0 or (f.min() >= 0 and f.max() < n), "face index out of range"


def _check_rigid(t: Any) -> None:
  assert isinstance(t, np.ndarray) and t.dtype == np.float64 and t.shape == (4, 4), short_repr(t)
  io.check_rigid(t, "result")  # ValueError when not rigid


def check_pose(x: Any) -> None:
  """A rigid (4, 4), a non-empty {name: rigid} or a non-empty list of LogEntry."""
  if isinstance(x, dict):
    assert x and all(isinstance(k, str) for k in x)
    for t in x.values():
      _check_rigid(t)
  elif isinstance(x, list):
    assert x
    for e in x:
      assert isinstance(e, io.LogEntry) and all(isinstance(v, int) for v in e[:3])
      _check_rigid(e.transform)
  else:
    _check_rigid(x)


def check_frames(m: int) -> Callable[[Any], None]:
  """(frames (m, 3, 3) finite, orthonormal, det +1; valid (m,) bool)."""

  def check(out: Any) -> None:
    frames, valid = (np.asarray(a) for a in out)
    assert frames.shape == (m, 3, 3) and valid.shape == (m,) and valid.dtype == bool, \
        (frames.shape, valid.shape, valid.dtype)
    assert np.isfinite(frames).all()
    if m:
      np.testing.assert_allclose(frames @ frames.transpose(0, 2, 1), np.broadcast_to(
          np.eye(3), frames.shape), atol=1e-4)
      np.testing.assert_allclose(np.linalg.det(frames), 1.0, atol=1e-4)

  return check


def check_registration(r: Any) -> None:
  t = np.asarray(r.transform, np.float64)
  assert t.shape == (4, 4) and np.isfinite(t).all()
  io.check_rigid(t, "transform", atol=1e-3)


# ---------------------------------------------------------------------------------------------
# Byte- and line-level mutations shared by the formats. Each returns (bytes, label).


def truncate(data: bytes, rng: np.random.Generator) -> tuple[bytes, str]:
  cut = int(rng.integers(0, len(data)))
  return data[:cut], f"truncated at byte {cut}/{len(data)}"


def flip(data: bytes, rng: np.random.Generator) -> tuple[bytes, str]:
  b = bytearray(data)
  pos = rng.integers(0, len(b), int(rng.integers(1, 9)))
  for p in pos:
    b[p] = int(rng.integers(0, 256))
  return bytes(b), f"bytes {sorted(pos.tolist())} flipped"


def append_garbage(data: bytes, rng: np.random.Generator) -> tuple[bytes, str]:
  extra = rng.bytes(int(rng.integers(1, 64)))
  return data + extra, f"{len(extra)} random bytes appended"


def edit_lines(lines: list[bytes], rng: np.random.Generator, op: str) -> tuple[list[bytes], str]:
  """Deletes, duplicates or swaps random lines."""
  lines = list(lines)
  i = int(rng.integers(0, len(lines)))
  if op == "delete":
    label = f"line {i} {lines[i][:30]!r} deleted"
    del lines[i]
  elif op == "duplicate":
    label = f"line {i} {lines[i][:30]!r} duplicated"
    lines.insert(i, lines[i])
  else:
    j = int(rng.integers(0, len(lines)))
    lines[i], lines[j] = lines[j], lines[i]
    label = f"lines {i} and {j} swapped"
  return lines, label


def replace_token(text: bytes, rng: np.random.Generator, values: tuple[str, ...] = BAD_NUMBERS,
                  start: int = 0) -> tuple[bytes, str]:
  """Replaces one random whitespace-separated token after byte `start`."""
  spans = [m.span() for m in re.finditer(rb"\S+", text[start:])]
  a, b = spans[int(rng.integers(0, len(spans)))]
  new = str(rng.choice(values)).encode("latin-1")
  a, b = a + start, b + start
  return text[:a] + new + text[b:], f"token {text[a:b][:20]!r} at byte {a} -> {new[:20]!r}"


def write_file(tmp_path: Path, name: str, data: bytes) -> Path:
  p = tmp_path / name
  p.write_bytes(data)
  return p


def pick(rng: np.random.Generator, seq: Any) -> Any:
  return seq[int(rng.integers(0, len(seq)))]


def file_cases(tmp_path: Path, fmt: str, n: int, bases: list[tuple[str, bytes, dict]],
                mutations: list[Callable], byte_level: list[Callable], suffix: str,
                readers: list[Callable], check: Callable[[Any], None],
                rng: np.random.Generator) -> list[Case]:
  """n cases: mutation i % len(mutations) (each is covered) on a random base; a quarter of the
  cases get a second, byte- or line-level mutation (their outcome is then 'either')."""
  cases = []
  for i in range(n):
    base_label, data, info = pick(rng, bases)
    data, label, outcome = mutations[i % len(mutations)](data, rng, info)
    if byte_level and rng.random() < 0.25 and data:
      data, more = pick(rng, byte_level)(data, rng)
      label, outcome = f"{label}; {more}", "either"
    path = write_file(tmp_path, f"{fmt}{i:03d}{suffix if not info.get('gz') else suffix + '.gz'}",
                  data)
    reader = readers[i % len(readers)]
    cases.append(Case(f"{path.name} [{base_label}] {label}", lambda r=reader, p=path: r(p),
                      str(path), check, outcome))
  return cases


def header_op(split: Callable[[bytes], tuple[list[bytes], bytes]], op: str) -> Callable:
  def mutate(data: bytes, rng: np.random.Generator, info: dict) -> tuple[bytes, str, str]:
    head, body = split(data)
    head, label = edit_lines(head, rng, op)
    return b"".join(head) + body, f"header {label}", "either"
  return mutate


def simple_mutation(fn: Callable, outcome: str | Callable[[dict], str] = "either") -> Callable:
  def mutate(data: bytes, rng: np.random.Generator, info: dict) -> tuple[bytes, str, str]:
    out, label = fn(data, rng)
    return out, label, outcome(info) if callable(outcome) else outcome
  return mutate


def binary_must_fail(info: dict) -> str:
  return "error" if info.get("binary") else "either"


def empty_file(data: bytes, rng: np.random.Generator, info: dict) -> tuple[bytes, str, str]:
  return b"", "empty file", "error"


def rejects(call: Callable[[], Any], name: str, *fragments: str, file: bool = True) -> None:
  """`call` passes the oracle as a case that must fail, and its message holds `fragments`."""
  why = judge(Case("regression", call, name, lambda r: None, "error", file))
  assert why is None, why
  with pytest.raises((ValueError, FileNotFoundError)) as info:
    call()
  for f in fragments:
    assert f in str(info.value), (f, str(info.value))


class FakeRegistration:
  """What the command lines read of a `Registration`, for tests of the command lines (the
  registration itself is not under test): a claimed identity."""
  transform = np.eye(4)
  n_inliers, correspondences, chance_inliers = 10, [0] * 20, 1.0
  overlap_contrast, fitness, rmse, mr, seconds, success = 3.0, 0.9, 0.1, 1.0, 0.1, True
  rival_inliers, overlap, reason = 1, 0.9, "a fake"

  def summary(self, gt=None):
    return "verdict: success: a fake"

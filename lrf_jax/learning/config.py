"""Training configuration: one frozen dataclass, presets in `lrf_jax/learning/configs/`, CLI overrides."""

from __future__ import annotations

import dataclasses
import importlib.util
import json
import math
from pathlib import Path
from typing import Any

from lrf_jax.checks import validate_seed
from lrf_jax.defaults import RADIUS_MR


@dataclasses.dataclass(frozen=True)
class TrainConfig:
  """Everything a training run depends on. The defaults are the paper's (section 3.1).

  Attributes:
    name: preset name, recorded with checkpoints.
    seed: the one seed of the run (keypoints, subsamples, shuffling, initialisation).
    data: "br" (noise-free BR: each model vs itself under each scene's ground truth), "demo"
      (the procedural set that ships as code; no download), "scans" (the overlapping pairs of
      the scan sets in `scans`, `lrf_jax.datasets.scan_sets`) or "br+scans" (both: a share
      `scan_share` of the training keypoints on the scans, the rest on BR). A config that gives
      `scans` without naming `data` (a `scans=DIR` override, a JSON config) trains on the scans
      alone: `replace` sets data to "scans".
    scans: folders of the user's own scans, each with its pose file (poses.txt, gt.log or a
      .conf; see `lrf_jax.datasets.scan_sets`); their overlapping pairs train. On the command
      line `scans=DIR[,DIR...]` (no comma in a path).
    val_scans: folders whose pairs validate instead of the bunny scans. Empty: with several
      `scans` folders the last one validates (and does not train); with one, the folder is split
      by scan (`lrf_jax.datasets.split_by_scan`: the pairs among its last 20 % of scans in name
      order validate, those among the others train). `val_pairs=0` trains on every pair.
    scan_share: with data "br+scans", the fraction of `num_train_keypoints` drawn on the scans.
    scan_min_overlap: the overlap a scan pair needs to train or validate (fraction of the
      source's points; `datasets.read_scan_set`'s `min_overlap`, 0.3 by default): lower it for
      a set of low-overlap pairs (3DLoMatch's are 10-30 %).
    scan_match_mr: how close (in mr) a scene point must lie to a model point under the ground
      truth for the two to train as a corresponding pair (`datasets.training_correspondences`;
      0.5, the repeatability protocol's rule). Scans voxelised on their own grids, such as
      3DMatch's 2.5 cm fragments, have almost no points that close: 1.0 there.
    data_root: where the data lives (None: LRF_DATA, then data/ in the repo).
    num_train_keypoints: size of the fixed, seeded set of training keypoints; one epoch is one
      pass over it.
    patch_k: points sampled per patch (256 in the paper), independently on each side.
    radius_mr: support radius in mesh resolutions (15).
    batch_size: pairs per step (512).
    epochs: number of epochs (20).
    learning_rate: Adam's initial learning rate (1e-4).
    lr_decay: multiplicative decay applied once per epoch (0.95 = "5% every epoch").
    loss_reduction: Chamfer form, "min" (eq. eq_cham, the paper), "max" or "sum".
    widths: encoder widths of the weight network.
    z_mode: "normal" (paper: the TOLDI normal over r/3) or "dr" (regressed; ablation).
    z_sign: "toldi" (paper: sign from the r/3 neighbors) or "ball" (sign over the whole
      support; lrf_net_plus, beyond the paper).
    z_view: "none" (z_sign decides everywhere) or "voted" (beyond the paper: lrf_net_plus from
      the points alone): each batch carries, per side, the view direction that inference's
      `lrf_net_plus.prepare_view` computes without a viewpoint, faces or normals
      (`lrf_net_plus.points_only_view`: normals oriented over the whole cloud by convexity
      votes, summed over the z support; 0 where the vote is not trusted), and z is flipped to
      agree with it where it is non-zero (`lrf_net.view_sign`), as at inference; validation
      orients z the same way. Needs the paper's model (z_mode "normal"; x_mode "sum", "max"
      or "softmax").
    x_mode: "sum" (paper, the ablation's "Sum1"), "sum2", "dr" or "max" (ablation, see
      `lrf_jax.frames.ablation`; "max" has no gradient and reuses weights trained for "sum"), or
      "softmax" (beyond the paper: the outputs are log-weights, `lrf_net.softmax_weights`).
    noise_mr: augmentation beyond the paper: Gaussian noise (in mr) added to the scene side, as
      a list to draw from per batch; () = none (the paper).
    crop_p: partiality augmentation beyond the paper: the probability that a training patch (each
      side independently) is cut by a random plane, as a scan boundary cuts a support (see
      `batches.crop_patches`); 0 = none (the paper).
    crop_min: the cut plane's smallest distance from the keypoint, as a fraction of r (the
      distance is uniform in [crop_min, 1)).
    val_pairs: number of validation pairs (0 disables): Stanford bunny scan pairs, or with scans
      the first pairs of the held-out scans.
    val_keypoints: keypoints per validation pair.
    init: where the parameters start: "" (default: initialised from `seed`), a shipped weights
      kind ("objects", "rooms", "streets": lrf_net_plus's files for x_mode "softmax", else
      lrf_net's; `frames.weights.weights_file`) or a parameter file's path (fine-tuning). The
      file must hold this model's parameters (the same layers and widths).
    log_every: steps between logged metrics.
    checkpoint_every: steps between checkpoints (the end of every epoch is always saved).
  """

  name: str = "default"
  seed: int = 0
  data: str = "br"
  data_root: str | None = None
  scans: tuple[str, ...] = ()
  val_scans: tuple[str, ...] = ()
  scan_share: float = 0.5
  scan_min_overlap: float = 0.3
  scan_match_mr: float = 0.5
  num_train_keypoints: int = 20_000
  patch_k: int = 256
  radius_mr: float = RADIUS_MR
  batch_size: int = 512
  epochs: int = 20
  learning_rate: float = 1e-4
  lr_decay: float = 0.95
  loss_reduction: str = "min"
  widths: tuple[int, ...] = (16, 32, 64)
  z_mode: str = "normal"
  z_sign: str = "toldi"
  z_view: str = "none"
  x_mode: str = "sum"
  noise_mr: tuple[float, ...] = ()
  crop_p: float = 0.0
  crop_min: float = 0.3
  val_pairs: int = 9
  val_keypoints: int = 500
  init: str = ""
  log_every: int = 10
  checkpoint_every: int = 200

  # Fields that change the shape or meaning of the parameters: a checkpoint written under other
  # values cannot be resumed.
  MODEL_FIELDS = ("widths", "z_mode", "z_sign", "z_view", "x_mode")

  def __post_init__(self):
    if self.data not in DATA_SOURCES:
      raise ValueError(f"config.data: expected one of {', '.join(map(repr, DATA_SOURCES))}, got "
                       f"{self.data!r}")
    if self.loss_reduction not in ("min", "max", "sum"):
      raise ValueError(f"config.loss_reduction: expected 'min', 'max' or 'sum', got "
                       f"{self.loss_reduction!r}")
    if self.x_mode not in ("sum", "sum2", "dr", "max", "softmax"):
      raise ValueError(f"config.x_mode: expected 'sum', 'sum2', 'dr', 'max' or 'softmax', got "
                       f"{self.x_mode!r}")
    if self.z_sign not in ("toldi", "ball"):
      raise ValueError(f"config.z_sign: expected 'toldi' or 'ball', got {self.z_sign!r}")
    if self.z_mode not in ("normal", "dr"):
      raise ValueError(f"config.z_mode: expected 'normal' or 'dr', got {self.z_mode!r}")
    if self.z_view not in ("none", "voted"):
      raise ValueError(f"config.z_view: expected 'none' or 'voted', got {self.z_view!r}")
    if self.z_view != "none" and (self.z_mode != "normal"
                                  or self.x_mode not in ("sum", "max", "softmax")):
      raise ValueError(f"config.z_view: {self.z_view!r} orients the z of LRF-Net's own frames; "
                       f"expected z_mode 'normal' and x_mode 'sum', 'max' or 'softmax', got "
                       f"z_mode {self.z_mode!r} and x_mode {self.x_mode!r} (or z_view 'none')")
    if not (_is_number(self.crop_p) and _is_number(self.crop_min)
            and 0.0 <= self.crop_p <= 1.0 and 0.0 <= self.crop_min < 1.0):
      raise ValueError(f"config.crop_p / crop_min: expected crop_p in [0, 1] and crop_min in "
                       f"[0, 1), got {self.crop_p!r} / {self.crop_min!r}")
    for f in ("num_train_keypoints", "patch_k", "batch_size", "epochs", "val_keypoints",
              "log_every", "checkpoint_every"):
      v = getattr(self, f)
      if isinstance(v, bool) or not isinstance(v, int) or v < 1:
        raise ValueError(f"config.{f}: expected a positive integer, got {v!r}")
    validate_seed(self.seed, "config.seed")  # JAX's keys: a larger seed repeats a smaller one
    v = self.val_pairs
    if isinstance(v, bool) or not isinstance(v, int) or v < 0:
      raise ValueError(f"config.val_pairs: expected a non-negative integer, got {v!r}")
    for f in ("radius_mr", "learning_rate", "scan_match_mr"):
      v = getattr(self, f)
      if not _is_number(v) or not math.isfinite(v) or v <= 0:
        raise ValueError(f"config.{f}: expected a positive finite number, got {v!r}")
    if not (_is_number(self.lr_decay) and 0 < self.lr_decay <= 1):
      raise ValueError(f"config.lr_decay: expected a number in (0, 1], got {self.lr_decay!r}")
    if self.batch_size > self.num_train_keypoints:
      raise ValueError(f"config.batch_size: {self.batch_size} pairs per step is more than the "
                       f"{self.num_train_keypoints} training keypoints (num_train_keypoints; one "
                       "epoch is one pass over them): lower batch_size or raise "
                       "num_train_keypoints")
    for f in ("name", "data", "loss_reduction", "z_mode", "z_sign", "z_view", "x_mode", "init"):
      if not isinstance(getattr(self, f), str):
        raise ValueError(f"config.{f}: expected a string, got {getattr(self, f)!r}")
    if self.data_root is not None and not isinstance(self.data_root, str):
      raise ValueError(f"config.data_root: expected a path (string) or null, got "
                       f"{self.data_root!r}")
    for f in ("noise_mr", "widths", "scans", "val_scans"):
      if isinstance(getattr(self, f), list):
        object.__setattr__(self, f, tuple(getattr(self, f)))
      if not isinstance(getattr(self, f), tuple):
        raise ValueError(f"config.{f}: expected a list, got {getattr(self, f)!r}")
    if any(not (_is_number(v) and math.isfinite(v) and v >= 0) for v in self.noise_mr):
      raise ValueError(f"config.noise_mr: expected non-negative noise levels in mr, got "
                       f"{self.noise_mr!r}")
    if not self.widths or any(isinstance(v, bool) or not isinstance(v, int) or v < 1
                              for v in self.widths):
      raise ValueError(f"config.widths: expected positive integer layer widths, got "
                       f"{self.widths!r}")
    self._check_scans()
    if self.init and not is_paper_model_fields(self.z_mode, self.x_mode):
      raise ValueError(f"config.init: starts LRF-Net's weight network; expected z_mode 'normal' "
                       f"and x_mode 'sum', 'max' or 'softmax', got {self.z_mode!r} / "
                       f"{self.x_mode!r} (or init '')")

  @property
  def init_weights_stem(self) -> str:
    """The shipped file family a kind in `init` names: lrf_net_plus's for x_mode "softmax"."""
    return "lrf_net_plus" if self.x_mode == "softmax" else "lrf_net"

  def _check_scans(self) -> None:
    """The scan-set fields agree with `data` (see the class docstring)."""
    for f in ("scans", "val_scans"):
      if any(not isinstance(v, str) or not v.strip() for v in getattr(self, f)):
        raise ValueError(f"config.{f}: expected folder paths (strings), got {getattr(self, f)!r}")
    uses = "scans" in self.data.split("+")
    if uses and not self.scans:
      raise ValueError(f"config.scans: data {self.data!r} trains on scan sets; expected at "
                       "least one folder (scans=DIR[,DIR...])")
    if not uses and (self.scans or self.val_scans):
      field = "scans" if self.scans else "val_scans"
      raise ValueError(f"config.{field}: given, but data {self.data!r} does not read scan sets; "
                       "expected data 'scans' or 'br+scans' (or no scans)")
    shared = sorted(set(self.scans) & set(self.val_scans))
    if shared:
      raise ValueError(f"config.val_scans: expected folders that do not train, found {shared} in "
                       "scans too")
    if not (_is_number(self.scan_min_overlap) and 0.0 < self.scan_min_overlap <= 1.0):
      raise ValueError(f"config.scan_min_overlap: expected a fraction in (0, 1], got "
                       f"{self.scan_min_overlap!r}")
    if not (_is_number(self.scan_share) and 0.0 < self.scan_share < 1.0):
      raise ValueError(f"config.scan_share: expected a fraction in (0, 1), got "
                       f"{self.scan_share!r}")

  @property
  def steps_per_epoch(self) -> int:
    """Whole batches per pass over the training keypoints (the remainder is dropped)."""
    return max(1, self.num_train_keypoints // self.batch_size)

  @property
  def total_steps(self) -> int:
    return self.steps_per_epoch * self.epochs

  def to_json(self) -> str:
    return json.dumps(dataclasses.asdict(self), indent=2, sort_keys=True)

  @classmethod
  def from_dict(cls, d: dict[str, Any]) -> TrainConfig:
    """A config from a mapping of field values (a JSON config's object).

    Raises:
      ValueError: `d` is not a mapping, names unknown fields or holds a bad value.
    """
    if not isinstance(d, dict):
      raise ValueError(f"config: expected an object of field: value pairs, got "
                       f"{type(d).__name__}")
    return replace(cls(), **d)


def is_paper_model_fields(z_mode: str, x_mode: str) -> bool:
  """True when these fields give plain WeightNet parameters (`lrf_net_frames`; the rule of
  `train_step.is_paper_model`)."""
  return z_mode == "normal" and x_mode in ("sum", "max", "softmax")


# The values of `TrainConfig.data`.
DATA_SOURCES = ("br", "demo", "scans", "br+scans")


def with_new_defaults(saved: dict[str, Any]) -> dict[str, Any]:
  """A config read back from a run (its config.json, a checkpoint's config) with the fields it
  lacks, added to `TrainConfig` after it was written (e.g. `z_view`), at their defaults: the
  behaviour that run had. Other keys are kept as they are."""
  return {**json.loads(TrainConfig().to_json()), **saved}


def _is_number(v: Any) -> bool:
  """An int or float, not a bool (JSON's true is not a number)."""
  return isinstance(v, (int, float)) and not isinstance(v, bool)


def _coerce(field: dataclasses.Field, value: Any) -> Any:
  """Parse a CLI string into the type of `field`'s default; a JSON list becomes a tuple. Other
  values are checked by `TrainConfig.__post_init__`."""
  if not isinstance(value, str):
    if isinstance(field.default, tuple) and isinstance(value, list):
      return tuple(value)
    return value
  default = field.default
  if value.lower() in ("none", "null") and field.name == "data_root":
    return None
  try:
    if isinstance(default, bool):
      if value.lower() not in ("1", "0", "true", "false", "yes", "no"):
        raise ValueError(value)
      return value.lower() in ("1", "true", "yes")
    if isinstance(default, int):
      return int(value)
    if isinstance(default, float):
      return float(value)
    if isinstance(default, tuple) and field.name in ("scans", "val_scans"):
      return tuple(v.strip() for v in value.split(",") if v.strip())  # paths: no brackets
    if isinstance(default, tuple):
      items = [v for v in value.strip("()[]").split(",") if v.strip()]
      cast = float if field.name == "noise_mr" else int
      return tuple(cast(v) for v in items)
  except ValueError:
    kind = ("true/false" if isinstance(default, bool) else "an integer" if isinstance(default, int)
            else "a number" if isinstance(default, float) else "a comma-separated list")
    raise ValueError(f"config.{field.name}: expected {kind} (default {default!r}), got "
                     f"{value!r}") from None
  return value


def replace(config: TrainConfig, **overrides: Any) -> TrainConfig:
  """`dataclasses.replace` with a clear error for unknown keys and string values parsed.

  Overrides that give `scans` (non-empty) without `data` make a config whose data reads no scan
  set train on the scans alone (data "scans"): `train.py --config default scans=DIR` trains on
  DIR's pairs; `data=br+scans scans=DIR` mixes them with BR.

  Raises:
    ValueError: an override names no field of `TrainConfig` (the message lists the valid ones).
  """
  fields = {f.name: f for f in dataclasses.fields(TrainConfig)}
  unknown = sorted(set(overrides) - set(fields))
  if unknown:
    raise ValueError(f"config: unknown key(s) {unknown}; valid keys are {sorted(fields)}")
  values = {k: _coerce(fields[k], v) for k, v in overrides.items()}
  if values.get("scans") and "data" not in values and "scans" not in config.data.split("+"):
    values["data"] = "scans"
  return dataclasses.replace(config, **values)


def parse_overrides(tokens: list[str]) -> dict[str, str]:
  """["epochs=2", "batch_size=64"] -> {"epochs": "2", "batch_size": "64"}."""
  out = {}
  for tok in tokens:
    key, sep, value = tok.partition("=")
    if not sep:
      raise ValueError(f"override {tok!r}: expected key=value (e.g. epochs=2)")
    out[key.strip().lstrip("-").replace("-", "_")] = value
  return out


def preset_names() -> list[str]:
  """The names `load_config` takes as presets (`lrf_jax/learning/configs/NAME.py`), sorted."""
  presets = Path(__file__).parent / "configs"
  return sorted(p.stem for p in presets.glob("*.py") if not p.stem.startswith("_"))


def load_config(name_or_path: str) -> TrainConfig:
  """A preset by name (`lrf_jax/learning/configs/NAME.py`) or a config file (.py with `get_config()`,
  or .json).

  Raises:
    ValueError: no such preset or file, a folder, a file that does not parse, a .py without a
      `get_config()` returning a `TrainConfig`, or a bad value (each message names the file).
  """
  path = Path(name_or_path)
  if path.suffix in (".json", ".py") and path.exists() and not path.is_file():
    raise ValueError(f"--config {name_or_path!r}: is a folder; expected a preset name or a .py "
                     "or .json file")
  if path.suffix == ".json" and path.exists():
    try:
      d = json.loads(path.read_text())
    except UnicodeDecodeError as e:
      raise ValueError(f"--config {path}: not UTF-8 text ({e})") from None
    except json.JSONDecodeError as e:
      raise ValueError(f"--config {path}: not valid JSON: {e}") from None
    try:
      return TrainConfig.from_dict(d)
    except ValueError as e:
      raise ValueError(f"--config {path}: {e}") from None
  presets = Path(__file__).parent / "configs"
  if not (path.suffix == ".py" and path.exists()):
    path = presets / f"{name_or_path}.py"
    if name_or_path.startswith("_") or "/" in name_or_path or not path.exists():
      names = preset_names()
      raise ValueError(f"--config {name_or_path!r}: no such preset or file; presets are "
                       f"{names}, or give a path to a .py (with get_config()) or .json")
  spec = importlib.util.spec_from_file_location(f"lrf_jax_config_{path.stem}", path)
  assert spec is not None and spec.loader is not None  # a .py file gets a source loader
  module = importlib.util.module_from_spec(spec)
  try:
    spec.loader.exec_module(module)
  except Exception as e:  # a user's file: any error in it is theirs to see, named
    raise ValueError(f"--config {path}: failed to run ({type(e).__name__}: {e})") from None
  get_config = getattr(module, "get_config", None)
  if not callable(get_config):
    raise ValueError(f"--config {path}: defines no get_config() function (expected one "
                     "returning a lrf_jax.learning.config.TrainConfig)")
  try:
    config = get_config()
  except ValueError as e:
    raise ValueError(f"--config {path}: get_config(): {e}") from None
  except Exception as e:
    raise ValueError(f"--config {path}: get_config() failed ({type(e).__name__}: {e})") from None
  if not isinstance(config, TrainConfig):
    raise ValueError(f"--config {path}: get_config() returned a {type(config).__name__}; "
                     "expected a lrf_jax.learning.config.TrainConfig (TrainConfig(**fields))")
  return config

"""lrf_jax.batch.scoring: a registration job scored against its PAIRS.tsv's gt column
(`--criteria DEG,DIST`), the errors against a brute-force reference, ground truths projected
like an init."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lrf_jax import datasets
from lrf_jax.batch import jobs, scoring
from lrf_jax.cli import batch as batch_cli
from lrf_jax.io import write_xf
from lrf_jax.io.poses import format_matrix
from tests.test_batch import OPTS, tsv_rows, write_pairs


def _t(rotvec, shift) -> np.ndarray:
  t = np.eye(4)
  t[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
  t[:3, 3] = shift
  return t


@pytest.mark.parametrize("text, ok", [("15,0.3", (15.0, 0.3)), ("5, 2", (5.0, 2.0)),
                                      ("15", None), ("a,b", None), ("0,1", None),
                                      ("1,-2", None), ("nan,1", None), ("1,2,3", None)])
def test_parse_criteria(text, ok):
  if ok is None:
    with pytest.raises(ValueError, match="criteria"):
      scoring.parse_criteria(text)
  else:
    c = scoring.parse_criteria(text)
    assert (c.max_rotation_deg, c.max_translation) == ok


def test_errors_against_a_brute_force_reference():
  rng = np.random.default_rng(0)
  for _ in range(20):
    gt = _t(rng.normal(size=3), rng.normal(size=3))
    est = _t(rng.normal(size=3) * 0.1, rng.normal(size=3)) @ gt
    rot, trans = scoring.errors(est, gt)
    ref = np.degrees(Rotation.from_matrix(est[:3, :3].T @ gt[:3, :3]).magnitude())
    assert rot == pytest.approx(ref, abs=1e-6)
    assert trans == pytest.approx(np.linalg.norm(est[:3, 3] - gt[:3, 3]), rel=1e-12)


@pytest.fixture(scope="module")
def job(tmp_path_factory):
  """Two demo pairs (scene -> model) with their ground truths: one true, one a published-style
  truth off orthonormal by 4e-4 (projected), one turned 30 deg, one not a rotation."""
  folder = tmp_path_factory.mktemp("scored")
  rows = []
  for k in range(2):
    pair = datasets.make_demo_pair(k, seed=0, noise_mr=0.05, partial=True)
    np.save(folder / f"scene{k}.npy", pair.scene_points)
    np.save(folder / f"model{k}.npy", pair.model_points)
    truth = np.linalg.inv(pair.transform)
    write_xf(folder / f"gt{k}.txt", truth)
    rows.append((f"p{k}", f"scene{k}.npy", f"model{k}.npy", f"gt{k}.txt"))
  off = np.loadtxt(folder / "gt0.txt")
  off[:3, :3] *= 1 + 4e-4 / 2  # |RᵀR - I| about 4e-4
  np.savetxt(folder / "off.txt", off)
  turned = _t([0, 0, np.radians(30)], [0, 0, 0]) @ np.loadtxt(folder / "gt1.txt")
  write_xf(folder / "turned.txt", turned)
  bad = np.loadtxt(folder / "gt0.txt")
  bad[:3, :3] *= 1.1
  np.savetxt(folder / "bad.txt", bad)
  rows += [("p0off", "scene0.npy", "model0.npy", "off.txt"),
           ("p1turned", "scene1.npy", "model1.npy", "turned.txt"),
           ("p0bad", "scene0.npy", "model0.npy", "bad.txt"),
           ("p1none", "scene1.npy", "model1.npy", "")]
  return write_pairs(folder / "pairs.tsv", rows, header=("name", "source", "target", "gt"))


def test_a_job_with_a_gt_column_scores_every_pair(job, tmp_path):
  res = jobs.run_register(job, tmp_path / "out", progress=False, criteria="5,0.05", **OPTS)
  rows = {r["name"]: r for r in tsv_rows(tmp_path / "out" / "results.tsv")}
  assert all(rows[n]["status"] == "done" for n in rows)
  for name in ("p0", "p0off", "p1turned"):
    est = np.loadtxt(tmp_path / "out" / f"{name}.txt")
    gt = np.loadtxt(job.parent / {"p0": "gt0.txt", "p0off": "off.txt",
                                  "p1turned": "turned.txt"}[name])
    rot, trans = scoring.errors(est, gt)
    assert float(rows[name]["rotation_error_deg"]) == pytest.approx(rot, abs=0.05)
    assert float(rows[name]["translation_error"]) == pytest.approx(trans, rel=1e-3, abs=1e-6)
  assert rows["p0"]["right"] == rows["p0off"]["right"] == "True"
  assert rows["p1turned"]["right"] == "False"
  assert float(rows["p1turned"]["rotation_error_deg"]) > 25
  assert rows["p0bad"]["right"] == "" and "orthonormal" in rows["p0bad"]["error"]
  assert rows["p1none"]["right"] == rows["p1none"]["rotation_error_deg"] == ""
  c = res.counts
  claimed = sum(r["success"] == "True" for r in rows.values())
  false = sum(r["success"] == "True" and r["right"] == "False" for r in rows.values())
  assert c == dict(pairs=6, done=6, claimed=claimed, scored=4,
                   right=sum(r["right"] == "True" for r in rows.values()), false_claims=false)


def test_the_cli_prints_the_counts_as_the_rows_count_them(job, tmp_path, capsys):
  rc = batch_cli.main(["register", str(job), "--out", str(tmp_path / "out"), "--no-progress",
                       "--criteria", "5,0.05", "--keypoints", "600", "--correspondences",
                       "200"])
  assert rc == 0
  last = capsys.readouterr().out.strip().splitlines()[-1]
  rows = tsv_rows(tmp_path / "out" / "results.tsv")
  right = sum(r["right"] == "True" for r in rows)
  claimed = sum(r["success"] == "True" for r in rows)
  false = sum(r["success"] == "True" and r["right"] == "False" for r in rows)
  assert last == f"6 pairs: {right} right of 4 scored, {claimed} claimed, {false} false claims"
  assert batch_cli.main(["register", str(job), "--out", str(tmp_path / "o2"),
                         "--criteria", "5"]) == 2


def test_an_init_column_registers_each_pair_from_its_init_and_keys_it_by_content(tmp_path):
  """PAIRS.tsv's `init` column: the pair is `register(source, target, init=T, **options)` bit for
  bit, results.tsv names the init, an init that is not a rigid transform is that row's error
  (naming the column and the file), and a changed init file redoes its pair alone."""
  from lrf_jax.registration import register
  pair = datasets.make_demo_pair(0, seed=0, noise_mr=0.05, partial=True)
  np.save(tmp_path / "scene.npy", pair.scene_points)
  np.save(tmp_path / "model.npy", pair.model_points)
  truth = np.linalg.inv(pair.transform)  # scene -> model
  init = _t([0.0, 0.0, np.radians(8.0)], [0.0, 0.0, 0.0]) @ truth
  write_xf(tmp_path / "init.txt", init)
  bad = init.copy()
  bad[:3, :3] *= 1.1
  np.savetxt(tmp_path / "bad.txt", bad)
  pairs = write_pairs(tmp_path / "pairs.tsv",
                      [("from_init", "scene.npy", "model.npy", "init.txt"),
                       ("plain", "scene.npy", "model.npy", ""),
                       ("bad_init", "scene.npy", "model.npy", "bad.txt"),
                       ("no_init", "scene.npy", "model.npy", "nope.txt")],
                      header=("name", "source", "target", "init"))
  res = jobs.run_register(pairs, tmp_path / "out", progress=False, **OPTS)
  rows = {r["name"]: r for r in tsv_rows(tmp_path / "out" / "results.tsv")}
  assert res.ran == 4 and rows["from_init"]["status"] == rows["plain"]["status"] == "done"
  assert rows["from_init"]["init"] == str((tmp_path / "init.txt").resolve())
  assert rows["plain"]["init"] == ""
  ref = register(pair.scene_points, pair.model_points, init=np.loadtxt(tmp_path / "init.txt"),
                 **OPTS)
  assert (tmp_path / "out" / "from_init.txt").read_text() == format_matrix(ref.transform) + "\n"
  assert rows["from_init"]["success"] == str(bool(ref.success))
  assert rows["from_init"]["reason"] == ref.reason
  assert rows["bad_init"]["status"] == "error"
  assert "init" in rows["bad_init"]["error"] and "bad.txt" in rows["bad_init"]["error"]
  assert rows["no_init"]["status"] == "error"  # the item's fault: not retried as transient
  assert rows["no_init"]["error"].startswith("init: ") and "nope.txt" in rows["no_init"]["error"]
  # the same job again redoes nothing; a changed init redoes its pair alone
  again = jobs.run_register(pairs, tmp_path / "out", progress=False, **OPTS)
  assert again.ran == 0
  write_xf(tmp_path / "init.txt", truth)
  third = jobs.run_register(pairs, tmp_path / "out", progress=False, **OPTS)
  assert third.ran == 1
  rows = {r["name"]: r for r in tsv_rows(tmp_path / "out" / "results.tsv")}
  assert rows["from_init"]["reason"].startswith("refined from init")


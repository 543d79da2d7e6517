"""`MultiwayResult.summary()`, its one-line repr and `MultiwayEdge.outcome`: what a person reads
matches the result's fields."""

from __future__ import annotations

import re

import numpy as np
import pytest

from lrf_jax.multiway.result import SUMMARY_LEFT_OUT, MultiwayEdge, MultiwayResult


def _edge(i, j, verdict, accepted, residual=0.2):
  return MultiwayEdge(i=i, j=j, transform=np.eye(4), verdict=verdict, reason="", n_inliers=50,
                      overlap=0.5, rmse=0.1, residual_mr=residual, accepted=accepted)


def _result(names, edges, in_model, confident=None, work=None, timings=None):
  n = len(names)
  in_model = np.asarray(in_model, bool)
  poses = np.where(in_model[:, None, None], np.tile(np.eye(4), (n, 1, 1)), np.nan)
  return MultiwayResult(names=tuple(names), poses=poses, in_model=in_model, reference=0,
                        edges=tuple(edges), mr=0.5, seconds=12.345,
                        timings={"load": 1.0, "pairwise": 10.0, "graph": 0.001}
                        if timings is None else timings,
                        confident=None if confident is None else np.asarray(confident, bool),
                        work=work or {})


def _numbers(line):
  return [float(x) for x in re.findall(r"\d+(?:\.\d+)?", line)]


@pytest.fixture
def model():
  """a-b-c-d placed (d only through a "not sure" edge); e and f a group of their own; g with
  only a rejected and a "not sure" edge; h with no pair at all."""
  inf = float("inf")
  edges = [_edge(0, 1, "success", True, 0.1), _edge(1, 2, "success", True, 0.3),
           _edge(0, 2, "success", True, 0.2), _edge(2, 3, "not sure", True, 0.9),
           _edge(0, 3, "not sure", False, 7.0), _edge(4, 5, "success", True, inf),
           _edge(1, 6, "success", False, inf), _edge(2, 6, "not sure", False, inf),
           _edge(3, 6, "error", False, inf), _edge(0, 4, "error", False, inf)]
  return _result(list("abcdefgh"), edges, [1, 1, 1, 1, 0, 0, 0, 0],
                 confident=[1, 1, 1, 0, 0, 0, 0, 0],
                 work={"scans_described": 7, "pairs_registered": 8, "pairs_resumed": 2})


def test_outcome_of_each_edge():
  assert _edge(0, 1, "success", True).outcome == "accepted"
  assert _edge(0, 1, "not sure", True).outcome == "accepted_not_sure"
  assert _edge(0, 1, "success", False).outcome == "rejected"
  assert _edge(0, 1, "not sure", False).outcome == "unused"
  assert _edge(0, 1, "error", False).outcome == "error"


def test_summary_counts_match_the_result(model):
  lines = model.summary().splitlines()
  assert not model.summary().endswith("\n")
  placed = _numbers(lines[0])
  assert placed[:2] == [model.in_model.sum(), len(model.names)] == [4, 8]
  assert "frame of a" in lines[0] and "mr = 0.5" in lines[0]
  assert lines[1] == 'placed only through "not sure" edges (check them; edges.tsv\'s placement): d'
  assert model.placed_not_sure == ["d"]
  edge_line = next(line for line in lines if line.startswith("edges: "))
  outcomes = [e.outcome for e in model.edges]
  accepted, total, success, backed, rejected, unused, errors = _numbers(edge_line)
  assert (accepted, total) == (sum(e.accepted for e in model.edges), len(model.edges)) == (5, 10)
  assert (success, backed) == (outcomes.count("accepted"), outcomes.count("accepted_not_sure"))
  assert (rejected, unused, errors) == (outcomes.count("rejected"), outcomes.count("unused"),
                                        outcomes.count("error")) == (1, 2, 2)
  residual = next(line for line in lines if line.startswith("residuals"))
  kept = [e.residual_mr for e in model.edges if e.accepted and np.isfinite(e.residual_mr)]
  assert _numbers(residual)[:2] == pytest.approx([np.median(kept), max(kept)], abs=1e-3)
  assert residual.endswith("(c - d)")  # the largest: 0.9 mr
  assert next(line for line in lines if "pairs registered" in line) == (
      "8 pairs registered, 2 read from earlier runs' records; 7 scans described")
  assert lines[-1] == "time 12.35 s (load 1.00, pairwise 10.00)"  # stages under 5 ms left off


def test_summary_says_why_each_scan_is_left_out(model):
  why = {line.split(": ")[1]: line.split(": ", 2)[2] for line in model.summary().splitlines()
         if line.startswith("left out: ")}
  assert set(why) == set(model.left_out) == set("efgh")
  assert "only to scans left out too (f)" in why["e"] and "(e)" in why["f"]
  assert why["g"] == ('no accepted edge: 1 "success" edges rejected (they contradict the '
                      'model), 1 "not sure" edges the graph did not back, 1 pairs could not '
                      'be registered')
  assert why["h"] == "no pair with it was registered"


def test_summary_of_a_model_without_residuals_or_work():
  res = _result(["a", "b"], [_edge(0, 1, "error", False, float("inf"))], [1, 0], timings={})
  text = res.summary()
  assert "residuals" not in text and "pairs registered" not in text
  assert "left out: b: no accepted edge: 1 pairs could not be registered" in text
  assert text.splitlines()[-1] == "time 12.35 s"


def test_summary_names_the_scans_left_out_beyond_the_first_ones():
  n = SUMMARY_LEFT_OUT + 4
  names = [f"s{k}" for k in range(n)]
  res = _result(names, [], [1] + [0] * (n - 1))
  lines = res.summary().splitlines()
  assert sum(line.startswith("left out: s") for line in lines) == SUMMARY_LEFT_OUT
  assert lines[-3] == "left out: 3 more (s11, s12, s13)"


def test_repr_is_one_line(model):
  text = repr(model)
  assert text == "MultiwayResult(4/8 scans placed, 5/10 edges accepted, 12.35 s; .poses, .summary())"

"""The paper's evaluation protocols: repeatability experiments, reports and figures."""

from lrf_jax.evaluation.experiments import (DATASETS, EXPERIMENTS, EvalOptions, available,
                                            run_experiment)
from lrf_jax.evaluation.report import markdown_report, plot_figures, summarise, write_results
from lrf_jax.evaluation.repeatability import (EXACT_NETWORK, MAX_NEIGHBORS, MethodRun,
                                              PatchCache, correspondences, evaluate_pair,
                                              paper_options)

__all__ = [
    "DATASETS", "EXACT_NETWORK", "EXPERIMENTS", "EvalOptions", "MAX_NEIGHBORS", "MethodRun",
    "PatchCache", "available", "paper_options",
    "correspondences", "evaluate_pair", "markdown_report", "plot_figures", "run_experiment",
    "summarise", "write_results",
]

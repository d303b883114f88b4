"""Reports: the results table, the learning curves and the aggregates across games of a
set of runs.

- `runs`: find run directories (a run, or a sweep of runs), read them, group them into
  configurations (the seeds of each);
- `scores`: reference scores, human-normalised scores, the table's rows and the scores
  across games;
- `reference`: Dopamine's published curves and the "on track?" verdicts against them;
- `curves`: the learning curves and their figures (the reference and Nature Fig. 2's
  held-out figures drawn with them);
- `aggregate`: the aggregates across games with stratified bootstrap confidence
  intervals (IQM, median, mean, optimality gap), performance profiles and probabilities
  of improvement, computed with rliable; `aggregate_figures`: their figures;
- `tables`: what a report holds (`Report`), its CSV records, console table and results.md;
  `legend`: the prose of results.md (its legend, the on-track table's text);
- `write`: `build_report` and `write_report`, the only module with side effects: it plays
  missing final evaluations, inspects Q-values, writes the outputs and removes stale ones.

Imports point one way: scores and reference import runs, curves imports reference and
runs, aggregate imports runs and scores, aggregate_figures imports aggregate, legend
imports runs and reference, tables imports all of these but the figures, write imports
them all, and nothing but this file imports write.
"""

from dqnlab.analysis.report.aggregate import (
    DEFAULT_BOOTSTRAP_REPETITIONS,
    DEFAULT_BOOTSTRAP_SEED,
    STATISTICS,
    Aggregates,
    AggregateSettings,
    ConfigurationAggregate,
    Improvement,
    Interval,
    Profile,
    aggregate_scores,
    aggregate_statistics,
    fraction_above,
    probability_of_improvement,
    score_matrices,
)
from dqnlab.analysis.report.aggregate_figures import interval_figure, profile_figure
from dqnlab.analysis.report.curves import Curve, CurveSeries, curve_figure, learning_curves
from dqnlab.analysis.report.legend import LEGEND
from dqnlab.analysis.report.runs import (
    ALL_EQUAL,
    NOT_GROUPED,
    Group,
    PeriodicEvaluation,
    RunResults,
    find_runs,
    group_runs,
    label_keys,
    load_run,
)
from dqnlab.analysis.report.scores import (
    BASELINE_NAMES,
    BASELINES,
    SEED_PAPER_SCORES,
    ReferenceScores,
    ResultRow,
    SummaryRow,
    human_normalised,
    load_reference_scores,
    result_rows,
    summary_rows,
)
from dqnlab.analysis.report.tables import (
    Report,
    RunInspection,
    format_markdown,
    format_table,
)
from dqnlab.analysis.report.write import (
    AGGREGATE_FILES,
    AGGREGATES_CSV,
    IMPROVEMENT_CSV,
    Q_VALUES_DIR,
    RESULTS_CSV,
    RESULTS_MD,
    SUMMARY_CSV,
    build_report,
    final_network_evaluator,
    inspect_report_runs,
    write_report,
)

__all__ = [
    "AGGREGATES_CSV",
    "AGGREGATE_FILES",
    "ALL_EQUAL",
    "BASELINES",
    "BASELINE_NAMES",
    "DEFAULT_BOOTSTRAP_REPETITIONS",
    "DEFAULT_BOOTSTRAP_SEED",
    "IMPROVEMENT_CSV",
    "LEGEND",
    "NOT_GROUPED",
    "Q_VALUES_DIR",
    "RESULTS_CSV",
    "RESULTS_MD",
    "SEED_PAPER_SCORES",
    "STATISTICS",
    "SUMMARY_CSV",
    "AggregateSettings",
    "Aggregates",
    "ConfigurationAggregate",
    "Curve",
    "CurveSeries",
    "Group",
    "Improvement",
    "Interval",
    "PeriodicEvaluation",
    "Profile",
    "ReferenceScores",
    "Report",
    "ResultRow",
    "RunInspection",
    "RunResults",
    "SummaryRow",
    "aggregate_scores",
    "aggregate_statistics",
    "fraction_above",
    "final_network_evaluator",
    "build_report",
    "curve_figure",
    "find_runs",
    "format_markdown",
    "format_table",
    "group_runs",
    "human_normalised",
    "inspect_report_runs",
    "interval_figure",
    "label_keys",
    "learning_curves",
    "load_reference_scores",
    "load_run",
    "probability_of_improvement",
    "profile_figure",
    "result_rows",
    "score_matrices",
    "summary_rows",
    "write_report",
]

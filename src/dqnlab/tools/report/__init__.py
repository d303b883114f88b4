"""Reports: the results table and the learning curves of a set of runs.

- `runs`: find run directories (a run, or a sweep of runs), read them, group them into
  configurations (the seeds of each);
- `scores`: reference scores, human-normalised scores, the table's rows and the scores
  across games;
- `reference`: Dopamine's published curves and the "on track?" verdicts against them;
- `curves`: the learning curves and their figures (the reference and Nature Fig. 2's
  held-out figures drawn with them);
- `tables`: what a report holds (`Report`), its CSV records, console table and results.md;
- `write`: `build_report` and `write_report`, the only module with side effects: it plays
  missing final evaluations, inspects Q-values, writes the outputs and removes stale ones.

Imports point one way: scores and reference import runs, curves imports reference and
runs, tables imports those four, write imports them all, and nothing but this file
imports write.
"""

from dqnlab.tools.report.curves import Curve, CurveSeries, curve_figure, learning_curves
from dqnlab.tools.report.runs import (
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
from dqnlab.tools.report.scores import (
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
from dqnlab.tools.report.tables import LEGEND, Report, RunInspection, format_markdown, format_table
from dqnlab.tools.report.write import (
    Q_VALUES_DIR,
    RESULTS_CSV,
    RESULTS_MD,
    SUMMARY_CSV,
    best_network_evaluator,
    build_report,
    inspect_report_runs,
    write_report,
)

__all__ = [
    "ALL_EQUAL",
    "BASELINES",
    "LEGEND",
    "NOT_GROUPED",
    "Q_VALUES_DIR",
    "RESULTS_CSV",
    "RESULTS_MD",
    "SEED_PAPER_SCORES",
    "SUMMARY_CSV",
    "Curve",
    "CurveSeries",
    "Group",
    "PeriodicEvaluation",
    "ReferenceScores",
    "Report",
    "ResultRow",
    "RunInspection",
    "RunResults",
    "SummaryRow",
    "best_network_evaluator",
    "build_report",
    "curve_figure",
    "find_runs",
    "format_markdown",
    "format_table",
    "group_runs",
    "human_normalised",
    "inspect_report_runs",
    "label_keys",
    "learning_curves",
    "load_reference_scores",
    "load_run",
    "result_rows",
    "summary_rows",
    "write_report",
]

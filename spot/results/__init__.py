"""Results: runs in, tables and claim verdicts out (``spot tables``, ``spot report``, ``spot results``).

The Python entry (docs/python.md): :func:`load_runs` (runs as a DataFrame), :func:`table` (a paper
table) and :func:`claims_report` (the claims report), in :mod:`~spot.results.api`.

Read in this order:

* :mod:`~spot.results.load`: the one run loader (an MLflow store, or results CSVs) and
  :mod:`~spot.results.export` (runs exported to a CSV to commit);
* :mod:`~spot.results.select`: the one run selector (which runs count, experiment sets, arms as
  filters on method, variant, dataset and params), used by the tables and the report alike;
* :mod:`~spot.results.claims`: claims files, the questions the report answers, as data (the paper's
  claims ship as ``paper_claims.yaml``; a study's own claims sit in its folder);
* :mod:`~spot.results.compare` and :mod:`~spot.results.designs`: the tests (a difference of means,
  the runner-up, the query-count difference in differences), :mod:`~spot.results.dose` (the added
  term against the score), :mod:`~spot.results.report` (the report, as Markdown);
* :mod:`~spot.results.tables`, :mod:`~spot.results.table_format`, :mod:`~spot.results.paper`: the
  paper's tables with its numbers beside ours;
* :mod:`~spot.results.stats`: interval estimates and tests over seeds and datasets.
"""

from spot.results.api import claims_report, load_runs, table

__all__ = ["claims_report", "load_runs", "table"]

"""lmac_report: `lmac report` / `python -m lmac_report`: merge training runs, report IQM, median and
mean of the final scores with stratified-bootstrap confidence intervals (rliable's method),
performance profiles and sample-efficiency curves, and write the runs as marl-eval JSON.

`runs` finds and reads runs, `stats` holds the statistics, `cli` the command line."""

from .runs import ReportError, Run, load_all, merged  # noqa: F401

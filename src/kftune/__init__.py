"""kftune — automatic tuning of Kalman filters.

Data → filter → cost → optimiser → report, one direction:

* :mod:`kftune.vehicle` — single-track model with Dugoff tyres
* :mod:`kftune.filters` — the unscented Kalman filter (compiled kernel + reference path)
* :mod:`kftune.data` — manoeuvres, loading/validation, the reference-data generator
* :mod:`kftune.bo` — surrogates (GP, Student-t process) and acquisition functions
* :mod:`kftune.optim` — TSBO and baselines behind one ask/tell interface; persistent studies
* :mod:`kftune.tuning` — the filter-tuning problem: parameter space, cost, KPIs
* :mod:`kftune.report` — paper-style tables and figures
"""

__version__ = "0.1.0"

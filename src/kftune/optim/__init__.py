"""kftune.optim — TSBO and its baselines behind one ask/tell interface; persistent studies.

Knows nothing about vehicles or filters: it minimises a black box over a box.

* :class:`Space`/:class:`Param` — named bounds, linear or log10, mapped to [0, 1]^d;
* :class:`Optimizer` — ``ask() -> Trial``, ``tell(trial, value)``; one per method in
  :data:`METHODS`, built with :func:`make_optimizer`; :data:`DEFAULT_METHOD` is
  :class:`TrustRegionBO` (``"trbo"``), the paper's TSBO is ``"tsbo-tsp"``;
* :func:`minimize` — the loop on top, with failures, timeouts and SQLite studies;
  :class:`Execution` says how it evaluates (a timeout, or an engine and batches);
* :class:`TRBOSettings`, :class:`TSBOSettings` — TR-BO's and TSBO's settings as records
  (:func:`make_optimizer` builds them from options by name);
* :class:`OptimizeResult`/:class:`EvalRecord` — what a run leaves behind;
* :func:`minimize_widening` — follow-up runs on a wider box while the best point lies on
  a bound.
"""

from kftune.optim.base import ExhaustedError, Optimizer, Proposal, Trial
from kftune.optim.baselines import ManualPoints, RandomSearch
from kftune.optim.ga import GeneticAlgorithm
from kftune.optim.minimize import (
    BATCH_RULE,
    COMPARE_METHODS,
    DEFAULT_METHOD,
    MAX_BUDGET,
    MAX_TIMEOUT,
    METHODS,
    PAPER_METHODS,
    Execution,
    OptimizationInterrupted,
    make_optimizer,
    minimize,
)
from kftune.optim.peers import CMAES, OptunaGP, OptunaTPE, PeerUnavailableError
from kftune.optim.result import EvalRecord, OptimizeResult
from kftune.optim.study import (
    Study,
    StudyError,
    StudyInUseError,
    StudyWriteError,
    is_study,
    study_files,
)
from kftune.optim.trbo import TRBOSettings, TrustRegionBO
from kftune.optim.tsbo import TSBO, TSBOSettings
from kftune.optim.widen import minimize_widening
from kftune.space import Param, Space

__all__ = [
    "BATCH_RULE",
    "CMAES",
    "COMPARE_METHODS",
    "DEFAULT_METHOD",
    "MAX_BUDGET",
    "MAX_TIMEOUT",
    "METHODS",
    "PAPER_METHODS",
    "TSBO",
    "EvalRecord",
    "Execution",
    "ExhaustedError",
    "GeneticAlgorithm",
    "ManualPoints",
    "OptimizationInterrupted",
    "OptimizeResult",
    "Optimizer",
    "OptunaGP",
    "OptunaTPE",
    "Param",
    "PeerUnavailableError",
    "Proposal",
    "RandomSearch",
    "Space",
    "Study",
    "StudyError",
    "StudyInUseError",
    "StudyWriteError",
    "TRBOSettings",
    "TSBOSettings",
    "Trial",
    "TrustRegionBO",
    "is_study",
    "make_optimizer",
    "minimize",
    "minimize_widening",
    "study_files",
]

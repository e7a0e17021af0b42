"""Scenario sweeps and tuning on an engine (local or Ray).

- :func:`run_sweep`: a grid over a scenario builder's keyword arguments, each configuration
  one batch of seeds; :func:`write_sweep` writes ``sweep.csv``, ``sweep.json`` and a figure.
- :func:`tune` (Optuna, extra ``tune``): a search over a scenario's declared
   search space (its registry entry) on tuning seeds, the best and the default re-evaluated
  on evaluation seeds, the best recommended only when it beats the default there.
- ``engine="ray"`` (extra ``ray``) runs configurations or trials as Ray tasks; the numbers
  are those of the local engine.
"""

from torchcbf.sweep.engines import ENGINES, run_all
from torchcbf.sweep.evaluate import evaluate, objective, success
from torchcbf.sweep.params import builder_defaults, parse_grid, parse_value
from torchcbf.sweep.sweep import configurations, run_sweep, write_sweep
from torchcbf.sweep.tune import recommend, search_space, tune, write_tune

__all__ = [
    "ENGINES",
    "builder_defaults",
    "configurations",
    "evaluate",
    "objective",
    "parse_grid",
    "parse_value",
    "recommend",
    "run_all",
    "run_sweep",
    "search_space",
    "success",
    "tune",
    "write_sweep",
    "write_tune",
]

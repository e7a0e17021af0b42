"""Scenario sweeps and tuning on an engine (local or Ray).

- :func:`run_sweep`: a grid over a scenario builder's keyword arguments, each configuration
  one batch of seeds; :func:`write_sweep` writes ``sweep.csv``, ``sweep.json`` and a figure.
- :func:`tune` (Optuna, extra ``tune``): a search over a scenario's declared
  :data:`SEARCH_SPACES` on tuning seeds, re-evaluated on evaluation seeds.
- ``engine="ray"`` (extra ``ray``) runs configurations or trials as Ray tasks; the numbers
  are those of the local engine.
"""

from torchcbf.sweep.engines import ENGINES, run_all
from torchcbf.sweep.evaluate import evaluate, objective, success
from torchcbf.sweep.params import SCENARIOS, builder_defaults, parse_grid, parse_value
from torchcbf.sweep.sweep import configurations, run_sweep, write_sweep
from torchcbf.sweep.tune import SEARCH_SPACES, Dimension, search_space, tune, write_tune

__all__ = [
    "ENGINES",
    "SCENARIOS",
    "SEARCH_SPACES",
    "Dimension",
    "builder_defaults",
    "configurations",
    "evaluate",
    "objective",
    "parse_grid",
    "parse_value",
    "run_all",
    "run_sweep",
    "search_space",
    "success",
    "tune",
    "write_sweep",
    "write_tune",
]

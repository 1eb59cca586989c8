"""The Monte Carlo harness (Hydra app, drivers, aggregation, figures): the extra ``[harness]``."""

import importlib.util

#: The harness's own dependencies beyond the library's (pyproject.toml, extra ``harness``).
HARNESS_MODULES = ("hydra", "pyarrow", "tqdm", "tabulate", "matplotlib")

missing = [name for name in HARNESS_MODULES if importlib.util.find_spec(name) is None]
if missing:
    raise ImportError(f"the harness (experiments) needs {', '.join(missing)}: pip install 'mapmerge[harness]'")
del missing

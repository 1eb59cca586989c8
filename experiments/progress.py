"""Progress of a sweep: one overall bar besides each cell's.

A sweep run by Hydra's basic launcher (cells one after the other in this
process) shows one overall bar, ``sweep``: trials done of the trials still
to run (cached trials are taken off the total as each cell starts, so the
rate and ETA are those of computing), trials per second, time left, and
the cells done. Each cell's own bar sits below it. The totals come from
the sweep's jobs as ``experiments.preflight`` expanded them; a sweep
started another way shows the cells done without totals. Under a launcher
that runs cells in other processes (``hydra/launcher=joblib``) only the
cells' bars show.

Bars are off with ``mc.progress=false``, with ``hydra.verbose=false``
given on the command line, and in CI (the environment variable ``CI`` set
to ``true`` or ``1``, as CI services do).
"""

from __future__ import annotations

import os
import sys

#: Trials per job of the sweep about to start, as ``preflight`` expanded it (None: unknown).
_planned: list[int] | None = None
_bar = None
_cells = [0, 0]  # done, total (0: unknown)
_quiet = False


def in_ci() -> bool:
    """Whether the environment says this is a CI job (``CI=true`` or ``CI=1``)."""
    return os.environ.get("CI", "").strip().lower() in ("true", "1")


def set_quiet(hydra_overrides) -> None:
    """Turn bars off when the command line gave ``hydra.verbose=false`` (among Hydra's own overrides)."""
    global _quiet
    _quiet = any(o.replace(" ", "").lower() == "hydra.verbose=false" for o in hydra_overrides)


def enabled(mc_progress: bool) -> bool:
    """Whether bars show: ``mc.progress``, not quietened, not in CI."""
    return bool(mc_progress) and not _quiet and not in_ci()


def plan(trials_per_job) -> None:
    """Record the trials of each job of the sweep about to start."""
    global _planned
    _planned = None if trials_per_job is None else [int(n) for n in trials_per_job]


def start_sweep(config) -> None:
    """Open the overall bar for a multirun whose master config is ``config``."""
    global _bar
    from tqdm.auto import tqdm

    set_quiet(config.hydra.overrides.hydra)
    launcher = str(config.hydra.launcher.get("_target_", ""))
    if not enabled(config.mc.progress) or "basic" not in launcher.lower():
        return
    _cells[:] = [0, len(_planned) if _planned else 0]
    _bar = tqdm(total=sum(_planned) if _planned else None, unit="trial", desc="sweep", position=0,
                file=sys.stderr, dynamic_ncols=True)
    _show_cells()


def cell_started(cached: int) -> None:
    """A cell starts with ``cached`` of its trials already computed: they leave the total."""
    if _bar is not None and _bar.total is not None:
        _bar.total = max(_bar.total - cached, _bar.n)
        _bar.refresh()


def trials_done(count: int) -> None:
    if _bar is not None:
        _bar.update(count)


def cell_done() -> None:
    if _bar is not None:
        _cells[0] += 1
        _show_cells()


def end_sweep() -> None:
    global _bar, _planned
    if _bar is not None:
        _bar.close()
    _bar, _planned = None, None


def active() -> bool:
    """Whether an overall bar is open (the cells' own bars then sit below it and vanish when done)."""
    return _bar is not None


def _show_cells() -> None:
    done, total = _cells
    _bar.set_postfix_str(f"cells {done}/{total}" if total else f"cells {done}", refresh=True)

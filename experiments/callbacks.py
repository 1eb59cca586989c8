"""Hydra callback: aggregate a multirun's cells when every job succeeded.

A sweep's name is a collection: ``<sweep dir>/aggregate/`` is rebuilt, after
every multirun under that name, from every run below the sweep directory
(``experiments.aggregate`` takes the union of the distinct trials of a cell
run several times), so a later, smaller sweep never replaces an earlier
one's table. ``aggregate_dir=DIR`` instead aggregates exactly the runs this
multirun wrote (what the drivers that write ``results/`` ask for). The
sweep's overall progress bar opens and closes here (``experiments.progress``).
"""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path

from hydra.core.utils import JobStatus
from hydra.experimental.callback import Callback
from omegaconf import OmegaConf

from . import progress

log = logging.getLogger(__name__)


class AggregateOnMultirunEnd(Callback):
    """Aggregate every run under the sweep's name into ``<sweep dir>/aggregate`` (or this multirun's
    own runs into ``aggregate_dir``: ``aggregate.runs_since``)."""

    def __init__(self) -> None:
        self.failed = 0
        self.started = time.time()

    def on_multirun_start(self, config, **kwargs) -> None:
        self.started = time.time()
        progress.start_sweep(config)

    def on_job_end(self, config, job_return, **kwargs) -> None:
        if job_return.status != JobStatus.COMPLETED:
            self.failed += 1
        progress.cell_done()

    def on_multirun_end(self, config, **kwargs) -> None:
        progress.end_sweep()
        if self.failed:
            log.warning("%d job(s) failed: not aggregating", self.failed)
            return
        from .aggregate import aggregate, find_runs, runs_since

        sweep_dir = Path(config.hydra.sweep.dir)
        if config.aggregate_dir:
            runs, out = runs_since(sweep_dir, self.started), Path(config.aggregate_dir)
        else:
            runs, out = find_runs([sweep_dir]), sweep_dir / "aggregate"
        # The jobs are done, so every core the multirun used may read: the cells' own
        # mc.n_jobs (1 when the launcher runs cells in parallel) or the launcher's.
        launcher_jobs = int(OmegaConf.select(config, "hydra.launcher.n_jobs", default=None) or 1)
        n_jobs = max(config.mc.n_jobs, (os.cpu_count() or 1) if launcher_jobs < 0 else launcher_jobs)
        aggregate(runs, out, n_jobs=n_jobs)
        log.info("aggregated %d run(s) of %s into %s", len(runs), sweep_dir, out)

"""Hydra callback: aggregate a multirun's cells when every job succeeded."""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path

from hydra.core.utils import JobStatus
from hydra.experimental.callback import Callback
from omegaconf import OmegaConf

log = logging.getLogger(__name__)


class AggregateOnMultirunEnd(Callback):
    """Aggregate the runs this multirun wrote (not older runs in the same sweep dir).

    A job always rewrites its ``trials.parquet`` when it ends, even when every
    chunk was already done, so the runs of this multirun are those whose file
    is newer than the multirun's start.
    """

    def __init__(self) -> None:
        self.failed = 0
        self.started = time.time()

    def on_multirun_start(self, config, **kwargs) -> None:
        self.started = time.time()

    def on_job_end(self, config, job_return, **kwargs) -> None:
        if job_return.status != JobStatus.COMPLETED:
            self.failed += 1

    def on_multirun_end(self, config, **kwargs) -> None:
        if self.failed:
            log.warning("%d job(s) failed: not aggregating", self.failed)
            return
        from .aggregate import aggregate, find_runs

        sweep_dir = Path(config.hydra.sweep.dir)
        runs = [r for r in find_runs([sweep_dir]) if (r / "trials.parquet").stat().st_mtime >= self.started - 1]
        out = Path(config.aggregate_dir) if config.aggregate_dir else sweep_dir / "aggregate"
        # The jobs are done, so every core the multirun used may read: the cells' own
        # mc.n_jobs (1 when the launcher runs cells in parallel) or the launcher's.
        launcher_jobs = int(OmegaConf.select(config, "hydra.launcher.n_jobs", default=None) or 1)
        n_jobs = max(config.mc.n_jobs, (os.cpu_count() or 1) if launcher_jobs < 0 else launcher_jobs)
        aggregate(runs, out, n_jobs=n_jobs)
        log.info("aggregated %s into %s", sweep_dir, out)

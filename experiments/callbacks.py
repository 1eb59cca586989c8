"""Hydra callback: aggregate a multirun's cells when every job succeeded."""

from __future__ import annotations

import logging
from pathlib import Path

from hydra.core.utils import JobStatus
from hydra.experimental.callback import Callback

log = logging.getLogger(__name__)


class AggregateOnMultirunEnd(Callback):
    def __init__(self) -> None:
        self.failed = 0

    def on_job_end(self, config, job_return, **kwargs) -> None:
        if job_return.status != JobStatus.COMPLETED:
            self.failed += 1

    def on_multirun_end(self, config, **kwargs) -> None:
        if self.failed:
            log.warning("%d job(s) failed: not aggregating", self.failed)
            return
        from .aggregate import aggregate

        sweep_dir = Path(config.hydra.sweep.dir)
        out = Path(config.aggregate_dir) if config.aggregate_dir else sweep_dir / "aggregate"
        aggregate([sweep_dir], out)
        log.info("aggregated %s into %s", sweep_dir, out)

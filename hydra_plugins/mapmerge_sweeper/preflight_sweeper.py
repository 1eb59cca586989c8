"""Hydra's basic sweeper without its second check of jobs the command line already checked.

Before launching a sweep, Hydra's basic sweeper composes every job's config in
the driver, one after the other, to catch composition errors early (about
50 ms a job: 2 s of the 36-job Fig. 3 grid, with every worker idle); the
launcher then composes each job again where it runs. ``python -m
experiments.run`` has by then composed and validated every job of the command
itself (``experiments.preflight``), so this sweeper skips Hydra's check for a
batch of exactly the jobs the preflight passed in this process, and checks
any other batch as Hydra does. Sweeping and launching are the basic
sweeper's.
"""

# No `from __future__ import annotations`: Hydra runs plugin modules outside
# sys.modules, where dataclasses cannot resolve string annotations.
from dataclasses import dataclass
from typing import Sequence

from hydra._internal.core_plugins.basic_sweeper import BasicSweeper, BasicSweeperConf
from hydra.core.config_store import ConfigStore


@dataclass
class PreflightSweeperConf(BasicSweeperConf):
    _target_: str = "hydra_plugins.mapmerge_sweeper.preflight_sweeper.PreflightSweeper"


ConfigStore.instance().store(group="hydra/sweeper", name="preflight", node=PreflightSweeperConf,
                             provider="mapmerge")


class PreflightSweeper(BasicSweeper):
    """``BasicSweeper`` that trusts ``experiments.preflight`` for the jobs it validated."""

    def validate_batch_is_legal(self, batch: Sequence[Sequence[str]]) -> None:
        from experiments.preflight import was_validated

        if not was_validated(batch):
            super().validate_batch_is_legal(batch)

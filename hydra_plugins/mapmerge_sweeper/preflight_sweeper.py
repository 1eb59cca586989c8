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
import functools
from dataclasses import dataclass
from typing import Iterable, Sequence

# Hydra keeps its basic sweeper in _internal; subclassing it keeps its sweep semantics exactly.
from hydra._internal.core_plugins.basic_sweeper import BasicSweeper, BasicSweeperConf
from hydra.core.config_store import ConfigStore
from hydra.core.override_parser.overrides_parser import OverridesParser


@dataclass
class PreflightSweeperConf(BasicSweeperConf):
    _target_: str = "hydra_plugins.mapmerge_sweeper.preflight_sweeper.PreflightSweeper"


ConfigStore.instance().store(group="hydra/sweeper", name="preflight", node=PreflightSweeperConf,
                             provider="mapmerge")


#: Jobs (``job_key``) the command line's check validated in this process. (Set only after
#: Hydra's plugin scan, which may run this module again.)
VALIDATED: set = set()


def key_value(override) -> tuple:
    """A parsed override as (key, value) spelt as Hydra launches it (``mc.progress=False``)."""
    return override.get_key_element(), override.get_value_element_as_str()


def job_key(overrides: Iterable[str]) -> frozenset:
    """A job's task overrides as a set of (key, value), however they were spelt or ordered;
    ``hydra.*`` settings are not part of a job."""
    return frozenset(key_value(o) for o in _parser().parse_overrides(list(overrides)) if not o.is_hydra_override())


@functools.cache
def _parser() -> OverridesParser:
    return OverridesParser.create()  # a few milliseconds each: once, not once per job


def validated(jobs: Iterable[Sequence[str]]) -> None:
    """Record jobs (lists of overrides) as composed and validated."""
    VALIDATED.update(job_key(job) for job in jobs)


def was_validated(batch: Sequence[Sequence[str]]) -> bool:
    """Whether every job of a batch was recorded by ``validated``."""
    return bool(VALIDATED) and all(job_key(job) in VALIDATED for job in batch)


class PreflightSweeper(BasicSweeper):
    """``BasicSweeper`` that trusts ``validated`` for the jobs recorded there."""

    def validate_batch_is_legal(self, batch: Sequence[Sequence[str]]) -> None:
        if not was_validated(batch):
            super().validate_batch_is_legal(batch)

"""Typed config schemas (Hydra ConfigStore) with their range checks.

Every key has a type: choices (method, objective, layout, source, backend,
kind) are enums, so a wrong type or a value outside a choice (e.g.
``matcher.method=papr``) is refused by Hydra at composition, with the
allowed values listed. The ranges are checked in each dataclass's
``__post_init__``, which ``validate`` reaches through
``OmegaConf.to_object``: a value out of range raises ``ConfigError`` with
one line naming the key, the value and what is allowed, before any work
starts or any file is written.
"""

from __future__ import annotations

import dataclasses
import difflib
import importlib.util
import typing
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path

from hydra.core.config_store import ConfigStore
from omegaconf import OmegaConf, open_dict

from mapmerge.assignment import OBJECTIVES
from mapmerge.datasets import SOURCES
from mapmerge.matching import resolve_log_tau
from mapmerge.merging import METHODS
from mapmerge.simulate import LAYOUTS, ScenarioError, check_scenario


def _conf_dir() -> str:
    """The Hydra configs: ``conf/`` beside the package in a source checkout,
    ``experiments/conf`` in an installed copy."""
    here = Path(__file__).resolve().parent
    for candidate in (here.parent / "conf", here / "conf"):
        if (candidate / "config.yaml").is_file():
            return str(candidate)
    raise FileNotFoundError(f"no Hydra configs (config.yaml) in {here.parent / 'conf'} or {here / 'conf'}")


CONF_DIR = _conf_dir()


def _choices(name: str, values) -> type[StrEnum]:
    """An enum whose members are ``values`` (names equal to values: configs spell them plainly)."""
    return StrEnum(name, {v: v for v in values})


#: The library's own lists, so that a method added there is accepted here.
Method = _choices("Method", METHODS)
Objective = _choices("Objective", OBJECTIVES)
Layout = _choices("Layout", LAYOUTS)
Source = _choices("Source", SOURCES)
#: joblib backends the harness runs chunks on.
Backend = _choices("Backend", ("loky", "dask"))
#: Synthetic maps (mapmerge.simulate) or a real data set.
Kind = _choices("Kind", ("synthetic", "victoria_park"))
#: Pose indices of the Victoria Park drive (mapmerge.datasets).
VICTORIA_PARK_POSES = (1, 6966)


class ConfigError(ValueError):
    """A config value outside what the harness accepts."""


def _fail(key: str, value, allowed: str):
    raise ConfigError(f"{key}={value!r} is invalid: {allowed}")


@dataclass
class ScenarioConfig:
    # Synthetic maps (mapmerge.simulate) or real data (victoria_park: cut, source).
    kind: Kind = Kind.synthetic
    n_landmarks: int = 100
    overlap: float = 0.75
    snr_db: float = 40.0
    aspect: float = 1.0
    # Map q shares no landmark with map p (false-merge rates).
    unrelated: bool = False
    # "strip" (the paper's: unshared landmarks only outside the overlap) or
    # "interleaved" (each agent detects an overlap landmark with p_detect).
    layout: Layout = Layout.strip
    p_detect: float = 0.9
    # Spurious landmarks per map, as a fraction of n_landmarks.
    clutter: float = 0.0
    # Range-bearing-like noise: growth of the cross-range deviation away from the path (0: isotropic).
    anisotropy: float = 0.0
    # Victoria Park: pose index where agent q takes over, and how agents map.
    cut: int = 3483
    source: Source = Source.reference

    def __post_init__(self):
        if self.kind == Kind.victoria_park:
            first, last = VICTORIA_PARK_POSES
            if not first <= self.cut <= last:
                _fail("scenario.cut", self.cut, f"must be a pose index in [{first}, {last}]")
            if self.source == "slam" and importlib.util.find_spec("gtsam") is None:
                _fail("scenario.source", str(self.source), "needs GTSAM: pip install 'mapmerge[slam]'")
        try:
            check_scenario(self.n_landmarks, self.overlap, self.snr_db, self.aspect, str(self.layout), self.p_detect,
                           self.clutter, self.anisotropy)
        except ScenarioError as e:
            _fail(f"scenario.{e.argument}", e.value, e.rule)


@dataclass
class MatcherConfig:
    method: Method = Method.paper
    objective: Objective = Objective.lr
    # τ rules compared on the same trials: "oracle", "chi2:P" or a log-LR.
    taus: list[str] = field(default_factory=lambda: ["oracle", "chi2:0.01", "chi2:0.001"])
    # Pass the maps' per-landmark covariances (consensus's association and acceptance, fusion of every method).
    use_cov: bool = False
    # Also run the two oracle associations on every synthetic trial: the oracle
    # (true transform, noise model and prior; oracle_correct_pairs / oracle_wrong_pairs)
    # and the transform oracle (true transform only; transform_oracle_* columns).
    oracle: bool = False

    def __post_init__(self):
        if self.method == "astroalign" and importlib.util.find_spec("astroalign") is None:
            _fail("matcher.method", str(self.method), "needs the optional package: pip install 'mapmerge[baselines]'")
        taus = list(self.taus)
        if not taus:
            _fail("matcher.taus", taus, "must list at least one τ rule")
        if len(set(taus)) != len(taus):
            _fail("matcher.taus", taus, "must not repeat a rule")
        for rule in taus:
            if rule != "oracle":
                try:
                    resolve_log_tau(rule)
                except ValueError:
                    _fail("matcher.taus", rule, "each rule is 'oracle', 'chi2:P' with P in (0, 1), or a log-LR number")


@dataclass
class MCConfig:
    n_trials: int = 200
    n_jobs: int = 2
    # Upper bound on trials per chunk (a resume point); a cell is split into at
    # least n_jobs chunks. Larger chunks amortise per-chunk file I/O.
    chunk_size: int = 1000
    seed: int = 0
    backend: Backend = Backend.loky
    # dask.distributed scheduler address; null with backend=dask starts a LocalCluster.
    address: str | None = None
    # Trials whose full geometry is saved for Fig. 1 / Fig. 2 (0 = none).
    examples: int = 0
    progress: bool = True

    def __post_init__(self):
        for key in ("n_trials", "n_jobs", "chunk_size"):
            if getattr(self, key) < 1:
                _fail(f"mc.{key}", getattr(self, key), "must be >= 1")
        if self.seed < 0:
            _fail("mc.seed", self.seed, "must be >= 0")
        if self.address is not None and self.backend != Backend.dask:
            _fail("mc.address", self.address, "is only used with mc.backend=dask")
        if not 0 <= self.examples <= self.n_trials:
            _fail("mc.examples", self.examples, "must be between 0 and mc.n_trials")


@dataclass
class Config:
    name: str = "default"
    scenario: ScenarioConfig = field(default_factory=ScenarioConfig)
    matcher: MatcherConfig = field(default_factory=MatcherConfig)
    mc: MCConfig = field(default_factory=MCConfig)
    # Where aggregate tables land after a multirun (null: <sweep dir>/aggregate).
    aggregate_dir: str | None = None
    # Runs, sweeps, the trial cache shared by them and the results store live under it.
    output_root: str = "outputs"

    def __post_init__(self):
        if self.scenario.kind == Kind.victoria_park and self.mc.n_trials != 1:
            _fail("mc.n_trials", self.mc.n_trials, "must be 1 for a real data set (its maps are fixed)")


def register_configs() -> None:
    """Store the schema in Hydra's ConfigStore (``base_config``, the first entry of conf/config.yaml's defaults)."""
    ConfigStore.instance().store(name="base_config", node=Config)


def unknown_key(key: str, schema=Config) -> str | None:
    """None if ``key`` (dotted) is a field of the schema, else the nearest field's key ('' if none is near)."""
    parts = key.split(".")
    for i, part in enumerate(parts):
        hints = typing.get_type_hints(schema) if dataclasses.is_dataclass(schema) else {}
        if part not in hints:
            near = difflib.get_close_matches(part, list(hints), n=1)
            return ".".join(parts[:i] + near) if near else ""
        schema = hints[part]
    return None


def _leaf_keys(cfg, prefix: str = ""):
    for key in cfg:
        node = cfg[key]
        if OmegaConf.is_dict(node):
            yield from _leaf_keys(node, f"{prefix}{key}.")
        else:
            yield f"{prefix}{key}"


def validate(cfg) -> Config:
    """Check a composed config against the schema and its ranges.

    Parameters
    ----------
    cfg : DictConfig
        A composed config (``hydra`` settings, if present, are not checked).

    Returns
    -------
    Config
        The checked config as dataclasses.

    Raises
    ------
    ConfigError
        On the first bad key: a key the schema does not have (one added
        with ``+``, which composition accepts) or a value out of range.
    """
    cfg = cfg.copy()
    with open_dict(cfg):
        cfg.pop("hydra", None)
    for key in _leaf_keys(cfg):
        near = unknown_key(key)
        if near is not None:
            raise ConfigError(f"{key} is not a config key" + (f"; did you mean {near}?" if near else ""))
    return OmegaConf.to_object(cfg)

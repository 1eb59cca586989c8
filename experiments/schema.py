"""Structured config schemas (Hydra ConfigStore) and their range checks.

The dataclasses give every key a type, so unknown keys and wrong types are
rejected by Hydra at composition. ``validate`` adds the range checks and
raises ``ConfigError`` with one line naming the key, the value and what is
allowed, before any work starts or any file is written.
"""

from __future__ import annotations

import dataclasses
import difflib
import importlib.util
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

from hydra.core.config_store import ConfigStore


def _conf_dir() -> str:
    """The Hydra configs: ``conf/`` beside the package in a source checkout,
    ``experiments/conf`` in an installed copy."""
    here = Path(__file__).resolve().parent
    for candidate in (here.parent / "conf", here / "conf"):
        if (candidate / "config.yaml").is_file():
            return str(candidate)
    raise FileNotFoundError(f"no Hydra configs (config.yaml) in {here.parent / 'conf'} or {here / 'conf'}")


CONF_DIR = _conf_dir()

BACKENDS = ("loky", "dask")
KINDS = ("synthetic", "victoria_park")


class ConfigError(ValueError):
    """A config value outside what the harness accepts."""


@dataclass
class ScenarioConfig:
    # "synthetic" (mapmerge.simulate) or "victoria_park" (real data: cut, source).
    kind: str = "synthetic"
    n_landmarks: int = 100
    overlap: float = 0.75
    snr_db: float = 40.0
    aspect: float = 1.0
    # Map q shares no landmark with map p (false-merge rates).
    unrelated: bool = False
    # "strip" (the paper's: unshared landmarks only outside the overlap) or
    # "interleaved" (each agent detects an overlap landmark with p_detect).
    layout: str = "strip"
    p_detect: float = 0.9
    # Spurious landmarks per map, as a fraction of n_landmarks.
    clutter: float = 0.0
    # Range-bearing-like noise: growth of the cross-range deviation away from the path (0: isotropic).
    anisotropy: float = 0.0
    # Victoria Park: pose index where agent q takes over, and how agents map.
    cut: int = 3483
    source: str = "reference"


@dataclass
class MatcherConfig:
    method: str = "paper"
    objective: str = "lr"
    # τ rules compared on the same trials: "oracle", "chi2:P" or a log-LR.
    taus: list[str] = field(default_factory=lambda: ["oracle", "chi2:0.01", "chi2:0.001"])
    # Pass the maps' per-landmark covariances (consensus's association and acceptance, fusion of every method).
    use_cov: bool = False
    # Also run the two oracle associations on every synthetic trial: the oracle
    # (true transform, noise model and prior; oracle_correct_pairs / oracle_wrong_pairs)
    # and the transform oracle (true transform only; transform_oracle_* columns).
    oracle: bool = False


@dataclass
class MCConfig:
    n_trials: int = 200
    n_jobs: int = 2
    # Upper bound on trials per chunk (a resume point); a cell is split into at
    # least n_jobs chunks. Larger chunks amortise per-chunk file I/O.
    chunk_size: int = 1000
    seed: int = 0
    backend: str = "loky"
    # dask.distributed scheduler address; null with backend=dask starts a LocalCluster.
    address: Optional[str] = None
    # Trials whose full geometry is saved for Fig. 1 / Fig. 2 (0 = none).
    examples: int = 0
    progress: bool = True


@dataclass
class Config:
    name: str = "default"
    scenario: ScenarioConfig = field(default_factory=ScenarioConfig)
    matcher: MatcherConfig = field(default_factory=MatcherConfig)
    mc: MCConfig = field(default_factory=MCConfig)
    # Where aggregate tables land after a multirun (null: <sweep dir>/aggregate).
    aggregate_dir: Optional[str] = None


def register_configs() -> None:
    """Store the schema in Hydra's ConfigStore (``base_config``, the first entry of conf/config.yaml's defaults)."""
    ConfigStore.instance().store(name="base_config", node=Config)


def _fail(key: str, value, allowed: str):
    raise ConfigError(f"{key}={value!r} is invalid: {allowed}")


def unknown_keys(cfg, schema=Config, prefix: str = "") -> list[tuple[str, str | None]]:
    """Keys of ``cfg`` the schema does not have, each with the nearest valid key (or None)."""
    hints = typing.get_type_hints(schema)
    found = []
    for key in cfg.keys():
        if key == "hydra" and not prefix:
            continue
        if key not in hints:
            near = difflib.get_close_matches(str(key), list(hints), n=1)
            found.append((prefix + str(key), prefix + near[0] if near else None))
        elif dataclasses.is_dataclass(hints[key]):
            found += unknown_keys(cfg[key], hints[key], f"{prefix}{key}.")
    return found


def validate(cfg) -> None:
    """Check a composed config against the schema and the allowed ranges;
    raise ConfigError on the first bad key."""
    for key, near in unknown_keys(cfg):
        raise ConfigError(f"{key} is not a config key" + (f"; did you mean {near}?" if near else ""))
    # The library is imported only for the range checks, so that a mistyped key
    # or value is refused before numpy and scipy load.
    from mapmerge.datasets import SOURCES
    from mapmerge.matching import OBJECTIVES, resolve_log_tau
    from mapmerge.merging import METHODS
    from mapmerge.simulate import ScenarioError, check_scenario

    s, m, mc = cfg.scenario, cfg.matcher, cfg.mc
    if s.kind not in KINDS:
        _fail("scenario.kind", s.kind, f"must be one of {list(KINDS)}")
    if s.kind == "victoria_park":
        if not 1 <= s.cut <= 6966:
            _fail("scenario.cut", s.cut, "must be a pose index in [1, 6966]")
        if s.source not in SOURCES:
            _fail("scenario.source", s.source, f"must be one of {list(SOURCES)}")
        if s.source == "slam" and importlib.util.find_spec("gtsam") is None:
            _fail("scenario.source", s.source, "needs GTSAM: pip install -e '.[slam]'")
        if mc.n_trials != 1:
            _fail("mc.n_trials", mc.n_trials, "must be 1 for a real data set (its maps are fixed)")
    try:
        check_scenario(s.n_landmarks, s.overlap, s.snr_db, s.aspect, s.layout, s.p_detect, s.clutter, s.anisotropy)
    except ScenarioError as e:
        _fail(f"scenario.{e.argument}", e.value, e.rule)
    if m.method not in METHODS:
        _fail("matcher.method", m.method, f"must be one of {list(METHODS)}")
    if m.method == "astroalign" and importlib.util.find_spec("astroalign") is None:
        _fail("matcher.method", m.method, "needs the optional package: pip install -e '.[baselines]'")
    if m.objective not in OBJECTIVES:
        _fail("matcher.objective", m.objective, f"must be one of {list(OBJECTIVES)}")
    if len(m.taus) == 0:
        _fail("matcher.taus", list(m.taus), "must list at least one τ rule")
    if len(set(m.taus)) != len(m.taus):
        _fail("matcher.taus", list(m.taus), "must not repeat a rule")
    for rule in m.taus:
        if rule != "oracle":
            try:
                resolve_log_tau(rule)
            except ValueError:
                _fail("matcher.taus", rule, "each rule is 'oracle', 'chi2:P' with P in (0, 1), or a log-LR number")
    if mc.n_trials < 1:
        _fail("mc.n_trials", mc.n_trials, "must be >= 1")
    if mc.n_jobs < 1:
        _fail("mc.n_jobs", mc.n_jobs, "must be >= 1")
    if mc.chunk_size < 1:
        _fail("mc.chunk_size", mc.chunk_size, "must be >= 1")
    if mc.seed < 0:
        _fail("mc.seed", mc.seed, "must be >= 0")
    if mc.backend not in BACKENDS:
        _fail("mc.backend", mc.backend, f"must be one of {list(BACKENDS)}")
    if mc.address is not None and mc.backend != "dask":
        _fail("mc.address", mc.address, "is only used with mc.backend=dask")
    if not (0 <= mc.examples <= mc.n_trials):
        _fail("mc.examples", mc.examples, "must be between 0 and mc.n_trials")

"""Compose and validate every job of a command before Hydra creates anything.

``python -m experiments.run`` calls ``preflight`` first. Every job the
command would launch (every point of a sweep: the preset's
``hydra.sweeper.params``, then the command line's overrides, expanded as
Hydra's basic sweeper expands them) is composed with Hydra's compose API
and checked by ``experiments.schema.validate`` (a job that differs from the
sweep's base config only in plain values is that config with its values
set, which checks their types as composing does), so that a bad value
anywhere in a sweep stops it with one line naming the key, before a
directory is made or a trial runs. Only public Hydra APIs are used: the
override parser (``Override.sweep_string_iterator``) and ``hydra.compose``.
"""

from __future__ import annotations

import importlib.util
import itertools
from pathlib import Path

from .schema import CONF_DIR, ConfigError, register_configs, unknown_key, validate

#: Hydra launchers that ship in an optional extra of this package: option -> (plugin module, extra).
LAUNCHER_EXTRAS = {"submitit_slurm": ("hydra_plugins.hydra_submitit_launcher", "launchers"),
                   "submitit_local": ("hydra_plugins.hydra_submitit_launcher", "launchers")}


def preflight(argv: list[str]) -> list[int]:
    """Compose and validate every job a command would launch, writing nothing.

    Parameters
    ----------
    argv : list of str
        The command line of ``python -m experiments.run`` (without the program name).

    Returns
    -------
    list of int
        Each job's ``mc.n_trials``, in launch order (the sweep's progress totals).

    Raises
    ------
    ConfigError
        With one line naming the key, the value and what is allowed.
    """
    from hydra import compose, initialize_config_dir
    from hydra.core.override_parser.overrides_parser import OverridesParser

    overrides = [a for a in argv if not a.startswith("-")]
    multirun = any(a in ("-m", "--multirun") for a in argv)
    register_configs()
    try:
        parser = OverridesParser.create()
        parsed = parser.parse_overrides(overrides)
        check_overrides(parsed)
        with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
            if not multirun:
                jobs, base = [overrides], None
            else:
                plain = [o for o in parsed if not o.is_sweep_override()]
                base = compose("config", overrides=[o.input_line for o in plain], return_hydra_config=True)
                params = [f"{k}={v}" for k, v in (base.hydra.sweeper.get("params") or {}).items()]
                jobs = sweep_jobs(parser.parse_overrides(params) + parsed)
                applied = {(o.get_key_element(), o.get_value_element_as_str()) for o in plain}
            trials = []
            for job in jobs:
                cfg = None
                if base is not None:
                    rest = [o for o in parser.parse_overrides(job)
                            if (o.get_key_element(), o.get_value_element_as_str()) not in applied]
                    cfg = with_values(base, rest)
                if cfg is None:
                    cfg = compose("config", overrides=job, return_hydra_config=True)
                validate(cfg)
                check_launcher(cfg)
                trials.append(cfg.mc.n_trials)
    except ConfigError:
        raise
    except Exception as exc:  # Hydra's and OmegaConf's errors span several lines
        raise ConfigError(one_line(exc)) from None
    return trials


def sweep_jobs(overrides) -> list[list[str]]:
    """Every job of a sweep, as Hydra's basic sweeper forms them.

    Parameters
    ----------
    overrides : list of hydra.core.override_parser.types.Override
        Parsed overrides: the preset's sweep params, then the command line's.

    Returns
    -------
    list of list of str
        One list of ``key=value`` overrides per job, in Hydra's launch order
        (the cartesian product of the keys' values, in the keys' first order;
        a later value of a key replaces an earlier one).
    """
    values: dict[str, list[str]] = {}
    for o in overrides:
        key = o.get_key_element()
        spelt = o.sweep_string_iterator() if o.is_sweep_override() else [o.get_value_element_as_str()]
        values[key] = [f"{key}={v}" for v in spelt]
    return [list(job) for job in itertools.product(*values.values())]


def with_values(base, overrides):
    """``base`` with plain ``key=value`` overrides set, or None when one is anything else (a
    config group, ``+`` or ``~``, a value of the wrong type): composing each of a big sweep's
    jobs anew costs about 0.1 s a job (24 s of the 204-job ``compare`` preset), setting its
    values on one composed config almost nothing, with the same type checks."""
    from omegaconf import OmegaConf

    if any(o.is_add() or o.is_delete() or o.is_force_add() or o.package is not None or o.is_hydra_override()
           or Path(CONF_DIR, *o.key_or_group.split(".")).is_dir() for o in overrides):
        return None
    cfg = base.copy()
    try:
        for o in overrides:
            OmegaConf.update(cfg, o.key_or_group, o.value(), merge=False)
    except Exception:  # compose gives Hydra's own message
        return None
    return cfg


def check_overrides(overrides) -> None:
    """Refuse an override of a key the schema does not have (also one added with ``+``, which
    Hydra would accept), naming the nearest valid key, and a launcher whose extra is missing."""
    for o in overrides:
        key = o.key_or_group
        if key.startswith("hydra/launcher"):
            module, extra = LAUNCHER_EXTRAS.get(str(o.value()), (None, None))
            if module and importlib.util.find_spec(module) is None:
                raise ConfigError(f"{key}={o.value()} needs the launcher plugin: pip install 'mapmerge[{extra}]'")
        if o.is_hydra_override() or "/" in key or Path(CONF_DIR, *key.split(".")).is_dir():
            continue  # Hydra's own settings and config groups: Hydra checks their names
        near = unknown_key(key)
        if near is not None:
            raise ConfigError(f"{key} is not a config key" + (f"; did you mean {near}?" if near else ""))


def check_launcher(cfg) -> None:
    """Refuse workers inside a launcher that already runs jobs in parallel (joblib must not nest)."""
    launcher = str(cfg.hydra.launcher.get("_target_", ""))
    if "joblib" in launcher.lower() and cfg.mc.n_jobs != 1:
        raise ConfigError(f"mc.n_jobs={cfg.mc.n_jobs} is invalid: must be 1 under hydra/launcher=joblib "
                          "(the launcher already runs jobs in parallel; joblib must not nest)")


def one_line(exc: BaseException) -> str:
    """An exception and its causes (Hydra's composition errors span several lines) as one line."""
    parts = []
    while exc is not None:
        parts.append(" ".join(line.strip() for line in str(exc).splitlines() if line.strip()))
        exc = exc.__cause__
    return ": ".join(p for p in parts if p)

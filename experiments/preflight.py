"""Compose and validate every job of a command before Hydra creates anything.

``python -m experiments.run`` calls ``preflight`` first: each job of the
command (every point of a sweep) is composed and checked by
``experiments.schema.validate``, so a bad value anywhere in a sweep stops it
with one line naming the key, before a directory is made or a trial runs. A
sweep's jobs are composed from one base config with their plain
``key=value`` overrides applied, much faster than Hydra composes them.

The jobs it passed are handed to the sweeper (``hydra/sweeper: preflight``,
``hydra_plugins.mapmerge_sweeper``), which then need not compose them again.
"""

from __future__ import annotations

import dataclasses
import difflib
import re
import typing
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from .schema import CONF_DIR, ConfigError, register_configs, validate


def preflight(argv: list[str]) -> None:
    """Compose and validate every job a command would launch, writing nothing.

    Raises
    ------
    ConfigError
        With one line naming the key, the value and what is allowed.
    """
    from hydra import compose, initialize_config_dir
    from hydra.core.override_parser.overrides_parser import OverridesParser

    overrides = [a for a in argv if not a.startswith("-")]
    multirun = any(a in ("-m", "--multirun") for a in argv)
    try:
        parser = OverridesParser.create()
        parsed = parser.parse_overrides(overrides)
        jobs = [overrides]
        register_configs()
        # Imported after register_configs: Hydra's plugin scan must have run first (schema.register_configs).
        from hydra_plugins.mapmerge_sweeper.preflight_sweeper import key_value, validated

        with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
            if multirun:
                # Sweep values from the presets (hydra.sweeper.params) and the
                # command line expand exactly as Hydra's basic sweeper does.
                plain = [o for o in parsed if not o.is_sweep_override()]
                base = compose("config", overrides=[o.input_line for o in plain], return_hydra_config=True)
                params = [f"{k}={v}" for k, v in (base.hydra.sweeper.get("params") or {}).items()]
                sweep = parser.parse_overrides(params + overrides)
                jobs = expand_sweep(sweep)
                applied = {key_value(o) for o in plain}  # already in base
            for job in jobs:
                cfg = None
                if multirun:
                    cfg = _set_values(base, [o for o in parser.parse_overrides(job) if key_value(o) not in applied])
                if cfg is None:
                    cfg = compose("config", overrides=job, return_hydra_config=True)
                validate(cfg)
                launcher = str(cfg.hydra.launcher.get("_target_", ""))
                if "joblib" in launcher.lower() and cfg.mc.n_jobs != 1:
                    raise ConfigError(
                        f"mc.n_jobs={cfg.mc.n_jobs} is invalid: must be 1 under hydra/launcher=joblib "
                        "(the launcher already runs jobs in parallel; joblib must not nest)"
                    )
    except ConfigError:
        raise
    except Exception as exc:  # Hydra/OmegaConf composition errors are multi-line
        raise ConfigError(_one_line(exc)) from None
    validated(jobs)


def _one_line(exc: BaseException) -> str:
    """Hydra's composition error as one line naming the key and what is wrong."""
    causes = [exc]
    while causes[-1].__cause__ is not None:
        causes.append(causes[-1].__cause__)
    text = " ".join(line.strip() for line in str(causes[-1]).splitlines() if line.strip())
    wrong_type = re.search(r"Value '(.*?)' (?:of type '\w+' )?could not be converted to (\w+)", text)
    key = re.search(r"(?:full_key|override)[: ]+([\w.]+)", " ".join(str(c) for c in causes))
    if wrong_type and key:
        return f"{key[1]}={wrong_type[1]!r} is invalid: expected {_TYPE_NAMES.get(wrong_type[2], wrong_type[2])}"
    bad_bool = re.search(r"Value '(.*?)' is not a valid bool.*?full_key: ([\w.]+)", text)
    if bad_bool:
        return f"{bad_bool[2]}={bad_bool[1]!r} is invalid: expected true or false"
    missing = (re.search(r"Could not override '([\w.]+)'", text)
               or re.search(r"Key '\w+' not in '\w+'.*?full_key: ([\w.]+)", text))
    if missing:
        near = _nearest_key(missing[1])
        return f"{missing[1]} is not a config key" + (f"; did you mean {near}?" if near else "")
    return text


_TYPE_NAMES = {"Float": "a number", "Integer": "an integer", "Boolean": "true or false", "String": "a string"}


def _nearest_key(key: str) -> str | None:
    from .schema import Config

    schema, parts = Config, key.split(".")
    for part in parts[:-1]:
        hints = typing.get_type_hints(schema)
        if part not in hints or not dataclasses.is_dataclass(hints[part]):
            return None
        schema = hints[part]
    near = difflib.get_close_matches(parts[-1], list(typing.get_type_hints(schema)), n=1)
    return ".".join(parts[:-1] + near) if near else None


def expand_sweep(overrides) -> list[list[str]]:
    """Every job of a sweep (parsed ``overrides``: the preset's sweep params, then
    the command line's) as Hydra's basic sweeper forms and launches them: a
    later value of a key replaces an earlier one, values spelt as Hydra does."""
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper

    return [list(job) for job in BasicSweeper.split_arguments(overrides, None)[0]]


def _set_values(base: DictConfig, overrides) -> DictConfig | None:
    """``base`` with plain ``key=value`` overrides applied, or None when one
    is anything else (a config group, ``+``/``~``, a bad key or value):
    composing each of a big sweep's jobs from scratch costs seconds."""
    if any(o.is_add() or o.is_delete() or o.is_force_add() or o.package is not None
           or Path(CONF_DIR, *o.key_or_group.split(".")).is_dir() for o in overrides):
        return None
    cfg = base.copy()
    try:
        for o in overrides:
            OmegaConf.update(cfg, o.key_or_group, o.value(), merge=False)
    except Exception:  # let compose produce Hydra's own message
        return None
    return cfg

"""Helpers shared by the harness tests."""

import hashlib
import os
import subprocess
import sys
from pathlib import Path

from hydra import compose, initialize_config_dir

from experiments.run import CONF_DIR

ROOT = Path(__file__).resolve().parents[1]


def compose_config(overrides=(), hydra=False):
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose("config", overrides=list(overrides), return_hydra_config=hydra)


def digest(path):
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def small(**mc):
    """A 30-trial cell of 10-landmark maps."""
    overrides = ["scenario=small", "scenario.snr_db=25", "mc.n_trials=30", "mc.chunk_size=7",
                 "mc.progress=false"] + [f"mc.{k}={v}" for k, v in mc.items()]
    return compose_config(overrides)


def cli(args, cwd, timeout=120, **environ):
    """``python -m experiments.run ARGS`` in ``cwd`` (``environ``: variables set for it)."""
    env = {**os.environ, "PYTHONPATH": str(ROOT), **environ}
    return subprocess.run([sys.executable, "-m", "experiments.run", *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=timeout)

"""Regenerate the paper's Fig. 1-3 and tables into results/paper/ (the main job).

    python -m experiments.paper                 # reduced: 2,000 trials per ROC curve
    python -m experiments.paper --full          # the paper's 10,000 trials per curve
    python -m experiments.paper mc.n_jobs=1     # extra Hydra overrides go to every sweep

Runs three Hydra multiruns (presets ``fig3``, ``fig1``, ``fig2``), each
aggregated into ``results/paper/figN/`` as it ends, then draws the figures.
Finished chunks are reused, so a rerun after an interruption resumes.
"""

from __future__ import annotations

import argparse
import shlex
import subprocess
import sys
from pathlib import Path

from .figures import draw_all

#: Trials per ROC curve of the reduced default run (the paper used 10,000).
REDUCED_FIG3_TRIALS = 2000
FULL_FIG3_TRIALS = 10000


def _call(args: list[str]) -> None:
    cmd = [sys.executable, "-m", *args]
    print("+", shlex.join(cmd), flush=True)
    subprocess.run(cmd, check=True)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description="Regenerate the paper's figures and tables.")
    parser.add_argument("--full", action="store_true", help="10,000 trials per ROC curve, as in the paper")
    parser.add_argument("--out", default="results/paper", help="results directory (default results/paper)")
    parser.add_argument("overrides", nargs="*", help="extra Hydra overrides for every sweep")
    args = parser.parse_args(argv)
    out = Path(args.out)
    trials = FULL_FIG3_TRIALS if args.full else REDUCED_FIG3_TRIALS
    for fig, extra in (("fig3", [f"mc.n_trials={trials}"]), ("fig1", []), ("fig2", [])):
        _call(["experiments.run", "-m", f"experiment={fig}", *extra,
               f"aggregate_dir={out / fig}", "mc.progress=false", *args.overrides])
    for path in draw_all(out):
        print(path)


if __name__ == "__main__":
    main()

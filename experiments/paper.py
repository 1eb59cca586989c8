"""Regenerate the paper's Fig. 1-3 and tables into results/paper/ (the main job).

    python -m experiments.paper                 # the paper's 10,000 trials per ROC curve
    python -m experiments.paper --quick         # 2,000 trials per curve, into outputs/paper-quick
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

import pandas as pd

from .figures import draw_all

#: Trials per ROC curve: the paper's, and the ``--quick`` run's.
FULL_FIG3_TRIALS = 10000
QUICK_FIG3_TRIALS = 2000


def run_module(args: list[str]) -> None:
    """Run ``python -m <args>`` in a fresh process (each driver step, as a user would type it), echoing
    the command; a failure raises ``CalledProcessError``."""
    cmd = [sys.executable, "-m", *args]
    print("+", shlex.join(cmd), flush=True)
    subprocess.run(cmd, check=True)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description="Regenerate the paper's figures and tables.")
    parser.add_argument("--quick", action="store_true",
                        help="2,000 trials per ROC curve (default: 10,000 as in the paper)")
    parser.add_argument("--out", help="results directory (default results/paper; with --quick outputs/paper-quick, "
                        "so a quick run never overwrites the committed results)")
    parser.add_argument("overrides", nargs="*", help="extra Hydra overrides for every sweep")
    args = parser.parse_args(argv)
    out = Path(args.out or ("outputs/paper-quick" if args.quick else "results/paper"))
    trials = QUICK_FIG3_TRIALS if args.quick else FULL_FIG3_TRIALS
    for fig, extra in (("fig3", [f"mc.n_trials={trials}"]), ("fig1", []), ("fig2", [])):
        run_module(["experiments.run", "-m", f"experiment={fig}", *extra,
               f"aggregate_dir={out / fig}", "mc.progress=false", *args.overrides])
    print(fig3_summary(out / "fig3"))
    for path in draw_all(out):
        print(path)


def fig3_summary(fig3: Path) -> Path:
    """``summary.md``: AUC and, for the oracle and chi2:0.01 rules, missed
    detections, precision and merge success at 20-40 dB (the README's excerpt)."""
    keys = ["n_landmarks", "overlap", "snr_db"]
    table = pd.read_csv(fig3 / "table.csv")
    table = table[table.snr_db.isin([20.0, 30.0, 40.0])]
    wide = table.pivot_table(index=keys, columns="tau", values=["md_rate", "success_rate", "precision"])
    picks = [("md_rate", "oracle"), ("success_rate", "oracle"), ("precision", "chi2:0.01"),
             ("md_rate", "chi2:0.01"), ("success_rate", "chi2:0.01")]
    wide = wide[picks].set_axis([f"{value} ({rule})" for value, rule in picks], axis=1)
    auc = pd.read_csv(fig3 / "auc.csv").set_index(keys)[["auc"]]
    summary = auc.join(wide, how="inner").reset_index()
    path = fig3 / "summary.md"
    path.write_text(summary.to_markdown(index=False, floatfmt=".3g") + "\n")
    return path


if __name__ == "__main__":
    main()

"""Benchmarks against the project's speed and scale targets (results/bench.*).

    python -m experiments.bench            # everything (about 10 minutes on 2 cores)
    python -m experiments.bench --quick    # Fig. 3 grid at 1,000 trials per cell (not the target's 10,000)

Measured in one process run so that ratios are stable on a noisy machine:

1. per-trial cost of Fig. 3 cells (10 and 20 landmarks, 75 % overlap, 20 dB)
   against the floor measured on the same trials: the three
   ``scipy.spatial.Delaunay`` calls a trial must make (two maps, the truth);
2. the full Fig. 3 grid (4 panels x 9 SNR x 10,000 trials) wall time on 2
   workers, through the real CLI (startup, 36 Hydra jobs, chunk files,
   aggregation: everything the user waits for);
3. the speed-up of ``mc.n_jobs=2`` over ``mc.n_jobs=1`` on that same grid;
4. merge time and peak memory (fresh process each) of two maps of 10^3,
   10^4 and 10^5 landmarks (75 % overlap, 30 dB, ``method="consensus"``),
   with a log-log plot.

Writes ``bench.csv`` (one row per measurement), ``bench.md`` (targets next
to the numbers) and ``bench_scale.png``/``.pdf``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.spatial import Delaunay

from .trials import make_trial_pair, run_chunk

FIG3_MATCHER = {"method": "paper", "objective": "lr", "taus": ["oracle", "chi2:0.01", "chi2:0.001"]}
SIZES = (1_000, 10_000, 100_000)


def per_trial(n_landmarks: int, n_trials: int = 1000, chunk: int = 500, repeats: int = 5) -> dict:
    """Seconds per trial of a Fig. 3 cell and of its three Delaunay calls.

    The cell runs as the Fig. 3 preset runs it (chunks of ``chunk`` trials,
    so the batched engine). Trials and floor are timed alternately
    ``repeats`` times and the fastest of each kept, as ``timeit`` does, so
    a burst of load on a shared machine does not land on one side only.
    """
    scenario = {"kind": "synthetic", "n_landmarks": n_landmarks, "overlap": 0.75, "snr_db": 20.0,
                "aspect": 1.0, "unrelated": False}
    run_chunk(0, scenario, FIG3_MATCHER, 0, 20)  # warm-up
    maps = [make_trial_pair(0, scenario, k) for k in range(n_trials)]
    trial = floor = np.inf
    for _ in range(repeats):
        start = time.perf_counter()
        for a in range(0, n_trials, chunk):
            run_chunk(0, scenario, FIG3_MATCHER, a, min(a + chunk, n_trials))
        trial = min(trial, (time.perf_counter() - start) / n_trials)
        start = time.perf_counter()
        for sc in maps:
            Delaunay(sc.p), Delaunay(sc.q), Delaunay(sc.truth)
        floor = min(floor, (time.perf_counter() - start) / n_trials)
    return {"n_landmarks": n_landmarks, "trial_s": trial, "floor_s": floor, "ratio": trial / floor}


def _run_cli(args: list[str]) -> float:
    start = time.perf_counter()
    subprocess.run([sys.executable, "-m", "experiments.run", *args, "mc.progress=false"],
                   check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - start


def fig3_grid(trials: int, n_jobs: int) -> float:
    """Wall time of the whole Fig. 3 sweep through the CLI, aggregation included."""
    with tempfile.TemporaryDirectory() as tmp:
        return _run_cli(["-m", "experiment=fig3", f"mc.n_trials={trials}", f"mc.n_jobs={n_jobs}",
                         f"hydra.sweep.dir={tmp}", f"aggregate_dir={tmp}/aggregate"])


def fig3_trials(trials: int, n_jobs: int) -> float:
    """Seconds of ``run(cfg)`` summed over the 36 Fig. 3 cells, in this process:
    the Monte Carlo execution alone (no interpreter start, Hydra job
    bookkeeping or aggregation, which do not parallelise)."""
    from hydra import compose, initialize_config_dir

    from .run import CONF_DIR, run

    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfgs = [compose("config", overrides=["experiment=fig3", f"mc.n_trials={trials}", f"mc.n_jobs={n_jobs}",
                                             "mc.progress=false", f"scenario.n_landmarks={n}",
                                             f"scenario.overlap={o}", f"scenario.snr_db={s}"])
                for n in (10, 20) for o in (0.75, 0.5) for s in range(0, 45, 5)]
    with tempfile.TemporaryDirectory() as tmp:
        run(cfgs[0], f"{tmp}/warm-up")  # start the workers, as the CLI's first cell does
        start = time.perf_counter()
        for k, cfg in enumerate(cfgs):
            run(cfg, f"{tmp}/{k}")
        return time.perf_counter() - start


def one_size(n: int) -> dict:
    """Merge two n-landmark maps in this process; report time and peak RSS."""
    import resource

    import mapmerge as mm
    from mapmerge import metrics

    sc = mm.simulate.make_pair(n, 0.75, 30.0, rng=1)
    start = time.perf_counter()
    res = mm.merge_maps(sc.p, sc.q, sc.sigma, method="consensus")
    seconds = time.perf_counter() - start
    err = metrics.map_errors(sc, res)
    return {"n_landmarks": n, "merge_s": seconds,
            "peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6,
            "correct_pairs": err["correct_pairs"], "wrong_pairs": err["wrong_pairs"],
            "rot_err_deg": err["rot_err_deg"], "success": err["success"]}


def scale() -> list[dict]:
    rows = []
    for n in SIZES:
        out = subprocess.run([sys.executable, "-m", "experiments.bench", "--one-size", str(n)],
                             check=True, capture_output=True, text=True).stdout
        rows.append(json.loads(out.strip().splitlines()[-1]))
    return rows


def scale_figure(rows: list[dict], out: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .figures import STYLE, _save

    n = np.array([r["n_landmarks"] for r in rows], dtype=float)
    t = np.array([r["merge_s"] for r in rows])
    with plt.rc_context(STYLE):
        fig, ax = plt.subplots(figsize=(3.6, 3.0))
        ax.loglog(n, t, "o-", label="merge_maps, consensus (measured)")
        ref = n * np.log(n)
        ax.loglog(n, ref * t[-1] / ref[-1], "k--", lw=0.7, label="n log n (through the last point)")
        ax.loglog(n, n**2 * t[-1] / n[-1] ** 2, "k:", lw=0.7, label="n² (through the last point)")
        ax.set_xlabel("landmarks per map")
        ax.set_ylabel("seconds")
        ax.grid(alpha=0.3, which="both", lw=0.4)
        ax.legend(frameon=False, fontsize=6)
        fig.tight_layout()
        return _save(fig, out, "bench_scale")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description="Speed and scale benchmarks.")
    parser.add_argument("--out", default="results")
    parser.add_argument("--quick", action="store_true", help="Fig. 3 grid at 1,000 trials per cell, x10")
    parser.add_argument("--one-size", type=int, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.one_size:
        print(json.dumps(one_size(args.one_size)))
        return
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows, md = [], ["# Benchmarks", "", f"Machine: {os.cpu_count()} cores. Command: "
                    f"`python -m experiments.bench{' --quick' if args.quick else ''}`.", ""]

    md += ["## Per-trial cost of a Fig. 3 cell (target: <= 2x the Delaunay floor)", "",
           "| landmarks | per trial (ms) | floor: 3 Delaunay calls (ms) | ratio | target met |",
           "|---:|---:|---:|---:|:---|"]
    for n in (10, 20):
        r = per_trial(n)
        rows.append({"benchmark": "per_trial", **r})
        md.append(f"| {n} | {1e3 * r['trial_s']:.3f} | {1e3 * r['floor_s']:.3f} | {r['ratio']:.2f} | "
                  f"{'yes' if r['ratio'] <= 2 else 'no'} |")

    trials = 1000 if args.quick else 10_000
    wall = {jobs: fig3_grid(trials, jobs) for jobs in (2, 1)}
    mc = {jobs: fig3_trials(trials, jobs) for jobs in (2, 1)}
    rows.append({"benchmark": "fig3_grid", "trials_per_cell": trials, "n_jobs_2_s": wall[2],
                 "n_jobs_1_s": wall[1], "speedup": wall[1] / wall[2]})
    rows.append({"benchmark": "fig3_trials", "trials_per_cell": trials, "n_jobs_2_s": mc[2],
                 "n_jobs_1_s": mc[1], "speedup": mc[1] / mc[2]})
    grid = "36 cells x 10,000 trials" if trials == 10_000 else f"36 cells x {trials:,} trials (--quick; the targets are for 10,000)"
    md += ["", f"## Full Fig. 3 grid, {grid}, 2 workers, whole CLI run (target: < 180 s)", "",
           f"{wall[2]:.0f} s: target {'met' if wall[2] < 180 else 'not met'}.",
           "", "## n_jobs=2 over n_jobs=1 on the same grid (target >= 1.8x)", "",
           "| what is timed | n_jobs=1 (s) | n_jobs=2 (s) | speed-up | target met |", "|---|---:|---:|---:|:---|",
           f"| Monte Carlo execution: `run(cfg)` of the 36 cells | {mc[1]:.1f} | {mc[2]:.1f} | "
           f"{mc[1] / mc[2]:.2f}x | {'yes' if mc[1] / mc[2] >= 1.8 else 'no'} |",
           f"| whole CLI (adds start-up, Hydra's per-job bookkeeping, aggregation) | {wall[1]:.1f} | "
           f"{wall[2]:.1f} | {wall[1] / wall[2]:.2f}x | {'yes' if wall[1] / wall[2] >= 1.8 else 'no'} |"]

    md += ["", "## Large maps, 75 % overlap, 30 dB, consensus (target 10^5: < 10 s, < 2 GB)", "",
           "| landmarks per map | merge (s) | peak RSS (GB) | correct pairs | wrong pairs | rotation error (deg) |",
           "|---:|---:|---:|---:|---:|---:|"]
    big = scale()
    for r in big:
        rows.append({"benchmark": "scale", **r})
        md.append(f"| {r['n_landmarks']:,} | {r['merge_s']:.2f} | {r['peak_rss_gb']:.2f} | "
                  f"{r['correct_pairs']:,} | {r['wrong_pairs']:,} | {r['rot_err_deg']:.4f} |")
    last = big[-1]
    md += ["", f"10^5: {last['merge_s']:.1f} s, {last['peak_rss_gb']:.2f} GB: time target "
           f"{'met' if last['merge_s'] < 10 else 'not met'}, memory target "
           f"{'met' if last['peak_rss_gb'] < 2 else 'not met'}. Growth: ![scale](bench_scale.png)"]
    scale_figure(big, out)
    pd.DataFrame(rows).to_csv(out / "bench.csv", index=False, float_format="%.6g")
    (out / "bench.md").write_text("\n".join(md) + "\n")
    print((out / "bench.md").read_text())


if __name__ == "__main__":
    main()

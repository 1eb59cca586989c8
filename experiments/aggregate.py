"""Pool trials per cell into ROC curves and precision / missed-detection tables.

    python -m experiments.aggregate RUN_OR_SWEEP_DIR [...] --out DIR

Reads every ``trials.parquet`` / ``pairs.parquet`` below the given
directories and writes the tables below. Runs of the same cell are pooled:
other seeds add trials, and runs that overlap (a sweep extended to more
trials, or run again under its name) count each (seed, trial, τ rule) once,
their union; runs whose common trials differ are refused, naming them.

- ``roc.csv``: P_FA, P_D and log τ per cell (sampled on a fixed P_FA grid,
  plus every point of the curve's first rise);
- ``auc.csv``: AUC, P_D at zero false alarms and pair counts per cell;
- ``table.csv`` / ``table.md``: per cell and τ rule, TP, FP, MD, TN,
  precision, MD rate, achieved P_D / P_FA, recall against common triangles,
  merge success rate and combined-map RMSE;
- ``timing.csv``: median milliseconds per merge per cell and τ rule (apart,
  so that the other files are reproducible to the bit);
- ``examples_triangles.csv`` / ``examples_landmarks.csv`` when runs saved
  example geometry (``mc.examples``), for Fig. 1 and Fig. 2.

Each run also writes its own cell's rows of the first four
(``summary_*.parquet``, by ``run_summaries``, in its worker while other
jobs run), so a sweep's aggregation reads those small files rather than
every run's trials and pairs. A cell pooled from several runs, or a run
without them (older, or interrupted before writing them) or with
summaries another version of this code wrote, is computed from its trials
and pairs; the tables are the same bits either way.
"""

from __future__ import annotations

import argparse
import functools
import hashlib
from collections import Counter
from pathlib import Path

import joblib
import numpy as np
import pandas as pd
import pyarrow as pa

from mapmerge import metrics

from .trials import LATER_KEYS, TIME_COLUMNS

CELL = ["kind", "cut", "source", "n_landmarks", "overlap", "snr_db", "aspect", "unrelated", "layout", "p_detect",
        "clutter", "anisotropy", "method", "objective", "use_cov"]
#: P_FA values at which stored ROC curves are sampled (the full curve gives AUC).
PFA_GRID = np.unique(np.r_[0.0, np.logspace(-5, 0, 151), np.linspace(0, 1, 201)])


#: Columns added after the first release, with the value runs written before them had.
LATER_COLUMNS = {"use_cov": False, **LATER_KEYS}


def with_defaults(trials: pd.DataFrame) -> pd.DataFrame:
    """Runs written before a column existed ran at its first-release value."""
    return trials.assign(**{k: v for k, v in LATER_COLUMNS.items() if k not in trials})


def find_runs(dirs) -> list[Path]:
    runs = sorted({p.parent for d in dirs for p in Path(d).rglob("trials.parquet")})
    if not runs:
        raise FileNotFoundError(f"no trials.parquet below {', '.join(map(str, dirs))}")
    return runs


#: The tables a run summarises for its own cell, each in ``summary_<kind>.parquet``.
SUMMARIES = ("roc", "auc", "table", "timing")
_DIGEST_KEY = b"mapmerge.summary_digest"


def summary_path(run, kind: str) -> Path:
    return Path(run) / f"summary_{kind}.parquet"


@functools.cache
def summary_digest() -> bytes:
    """Digest of the code that makes the summaries (this module and the library's metrics): a summary
    written by other code is not read (its run is aggregated from its trials and pairs instead)."""
    digest = hashlib.sha256()
    for path in (Path(__file__), Path(metrics.__file__)):
        digest.update(path.resolve().read_bytes())
    return digest.hexdigest().encode()


def runs_since(sweep_dir, started: float) -> list[Path]:
    """The runs below ``sweep_dir`` that a multirun begun at ``started`` (``time.time()``) wrote: a job
    always rewrites its ``trials.parquet`` when it ends, even when every chunk was already done."""
    return [r for r in find_runs([sweep_dir]) if (r / "trials.parquet").stat().st_mtime >= started - 1]


def load_examples(dirs) -> dict[str, pd.DataFrame]:
    """Example-trial geometry tables of every run, tagged with their cell."""
    found: dict[str, list[pd.DataFrame]] = {}
    for run in find_runs(dirs):
        paths = sorted(run.glob("example_*.parquet"))
        if not paths:
            continue
        cell = dict(zip(CELL, _run_cell(run)))
        for path in paths:
            table = pd.read_parquet(path)
            # The table's own columns win (its "kind" is p / q / merged / truth).
            found.setdefault(path.stem, []).append(
                table.assign(**{k: v for k, v in cell.items() if k not in table.columns}))
    return {name: pd.concat(parts, ignore_index=True) for name, parts in found.items()}


def load(dirs, n_jobs: int = 1) -> tuple[pd.DataFrame, dict[tuple, pd.DataFrame]]:
    """All trials, and every cell's tentative pairs.

    Parameters
    ----------
    dirs : sequence of path
        Run or sweep directories.
    n_jobs : int
        Threads reading the runs (Parquet decoding releases the GIL).

    Returns
    -------
    trials : DataFrame
        One row per trial and τ rule, timings joined; a trial held by
        several runs of a cell appears once (``union``).
    pairs : dict
        Cell (tuple of the ``CELL`` values) -> its pairs from every run of
        it (each trial's once), with a ``seed`` column; cells in sorted order. Kept per cell, not
        as one frame with the cell repeated on millions of rows.
    """
    paths = find_runs(dirs)
    runs = joblib.Parallel(n_jobs=n_jobs, prefer="threads")(joblib.delayed(_load_run)(run) for run in paths)
    by_cell = {}
    for i, (t, _) in enumerate(runs):
        by_cell.setdefault(_cell(t), []).append(i)
    # A run never repeats a trial: only a cell with several runs can hold one twice.
    for cell, idx in by_cell.items():
        if len(idx) > 1:
            for i, (t, p) in zip(idx, union([paths[i] for i in idx], [runs[i] for i in idx], cell)):
                runs[i] = t, p
    # One conversion of all runs at once: concatenating Arrow tables copies nothing.
    trials = pa.concat_tables([t for t, _ in runs], promote_options="default").to_pandas()
    return trials, {cell: _once([runs[i][1] for i in by_cell[cell]]) for cell in sorted(by_cell)}


#: Trials shown by name when runs of a cell disagree.
SHOWN_CONFLICTS = 3


def union(paths, runs, cell) -> list[tuple[pa.Table, pd.DataFrame]]:
    """The runs of one cell with every (seed, trial, τ rule) kept once: the union of their trials.

    Runs of a cell overlap when a sweep is extended (more trials) or run
    again under the same name; their common trials are the same bits, so
    the first run that holds a trial supplies it.

    Parameters
    ----------
    paths : list of Path
        The runs' directories (named in the error).
    runs : list of (pyarrow.Table, DataFrame)
        Their trials and pairs, as ``_load_run`` gives them.
    cell : tuple
        The cell's ``CELL`` values.

    Returns
    -------
    list of (pyarrow.Table, DataFrame)
        Each run's trials without those an earlier run holds (its pairs as given: ``_once`` keeps
        one copy of each trial's pairs).

    Raises
    ------
    ValueError
        When a trial (or its triangle pairs) differs between two runs, e.g. runs of other code or
        another version of numpy: the trials are named and nothing is pooled.
    """
    common = sorted(set.intersection(*(set(t.column_names) for t, _ in runs)) - {*TIME_COLUMNS})
    frames = [t.select(common).to_pandas() for t, _ in runs]
    keys = pd.concat([f[["seed", "trial", "tau"]] for f in frames], ignore_index=True)
    keys["digest"] = np.concatenate([pd.util.hash_pandas_object(f, index=False).to_numpy() for f in frames])
    keys["run"] = np.repeat(np.arange(len(runs)), [len(f) for f in frames])
    first = keys.groupby(["seed", "trial", "tau"], sort=False)["digest"].transform("first")
    _refuse_conflicts(keys[keys.digest != first], keys, paths, cell, "trial")
    # The pairs of a trial (τ-independent) must agree too: compared by a digest of all its rows.
    pairs = pd.concat([p.assign(run=k, digest=pd.util.hash_pandas_object(
        p[["trial", "score", "label", "order_consistent"]], index=False).to_numpy())
        for k, (_, p) in enumerate(runs)], ignore_index=True)
    per_trial = pairs.groupby(["run", "seed", "trial"], sort=False).agg(digest=("digest", "sum"),
                                                                      n=("digest", "size")).reset_index()
    per_trial["digest"] = per_trial.digest.to_numpy(np.uint64) ^ per_trial.n.to_numpy(np.uint64)
    first = per_trial.groupby(["seed", "trial"], sort=False)["digest"].transform("first")
    _refuse_conflicts(per_trial[per_trial.digest != first], per_trial, paths, cell, "triangle pairs of trial")
    keep = ~keys.duplicated(["seed", "trial", "tau"]).to_numpy()
    bounds = np.r_[0, np.cumsum([len(f) for f in frames])]
    return [(t.filter(pa.array(keep[a:b])), p) for (t, p), a, b in zip(runs, bounds[:-1], bounds[1:])]


def _refuse_conflicts(bad: pd.DataFrame, rows: pd.DataFrame, paths, cell, what: str) -> None:
    if bad.empty:
        return
    shown = []
    for row in bad.head(SHOWN_CONFLICTS).itertuples():
        other = rows[(rows.seed == row.seed) & (rows.trial == row.trial)].run.iloc[0]
        rule = f", τ rule {row.tau}" if "tau" in rows else ""
        shown.append(f"{what} {row.trial} (seed {row.seed}{rule}) in {paths[other]} and {paths[row.run]}")
    raise ValueError(f"{len(bad)} trial(s) of cell {dict(zip(CELL, cell))} differ between runs (other code, "
                     f"library versions or settings): {'; '.join(shown)}; aggregate those runs apart")


def _once(parts: list[pd.DataFrame]) -> pd.DataFrame:
    """A cell's tentative pairs with every (seed, trial) counted once.

    Pairs do not depend on τ, so runs of one cell that differ only in their
    τ rules (a sweep over ``matcher.taus``) hold the same trials' pairs:
    the first run that has a trial supplies its pairs.
    """
    if len(parts) == 1:  # the usual case: nothing to drop, and no copy of millions of rows
        return parts[0]
    seen, kept = set(), []
    for part in parts:
        key = part["seed"].to_numpy(np.int64) * (1 << 32) + part["trial"].to_numpy(np.int64)
        new = ~np.isin(key, np.fromiter(seen, np.int64, len(seen)))
        kept.append(part[new])
        seen.update(np.unique(key[new]).tolist())
    return pd.concat(kept, ignore_index=True)


def _load_run(run: Path) -> tuple[pa.Table, pd.DataFrame]:
    """A run's trials (as Arrow, timings joined, columns it predates at their defaults) and its pairs."""
    import pyarrow.parquet as pq

    return _joined(run, *(pq.read_table(run / f"{kind}.parquet") for kind in ("trials", "timings", "pairs")))


def _joined(run, t: pa.Table, timings: pa.Table, pairs: pa.Table) -> tuple[pa.Table, pd.DataFrame]:
    # The run wrote both files from one table, so their rows match one to one.
    if not all(t.column(k).equals(timings.column(k)) for k in ("trial", "tau")):
        raise ValueError(f"{run}: timings.parquet does not match trials.parquet row for row")
    t = _with_later_columns(t)
    for name in TIME_COLUMNS:
        t = t.append_column(name, timings.column(name))
    return t, pairs.to_pandas().assign(seed=t.column("seed")[0].as_py())


def _with_later_columns(t: pa.Table) -> pa.Table:
    """A run's trials with the columns it predates at their first-release values."""
    for key, value in LATER_COLUMNS.items():
        if key not in t.column_names:
            t = t.append_column(key, pa.repeat(value, t.num_rows))
    return t


def _cell(table: pa.Table) -> tuple:
    return tuple(table.column(c)[0].as_py() for c in CELL)


def run_summaries(run, trials: pa.Table, timings: pa.Table, pairs: pa.Table) -> dict[str, pa.Table]:
    """One run's rows of each table in ``SUMMARIES``, from the tables it writes to its files, marked
    with ``summary_digest``."""
    t, p = _joined(run, trials, timings, pairs)
    out = {}
    for kind, frame in cell_tables(t.to_pandas(), {_cell(t): p}).items():
        table = pa.Table.from_pandas(frame, preserve_index=False)
        out[kind] = table.replace_schema_metadata({**table.schema.metadata, _DIGEST_KEY: summary_digest()})
    return out


def cell_tables(trials: pd.DataFrame, pairs: dict[tuple, pd.DataFrame], n_jobs: int = 1) -> dict[str, pd.DataFrame]:
    """The tables in ``SUMMARIES`` of the cells of ``trials`` and ``pairs`` (as from ``load``)."""
    roc, auc = roc_tables(pairs, n_jobs)
    return {"roc": roc, "auc": auc, "table": summary_table(trials), "timing": timing_table(trials)}


def aggregate_tables(runs, n_jobs: int = 1) -> dict[str, pd.DataFrame]:
    """The tables in ``SUMMARIES`` of some runs, cells in sorted order.

    A cell with one run that wrote its summaries reads them; every other
    cell is computed from its runs' trials and pairs (``load``).
    """
    import pyarrow.parquet as pq

    summaries = {}
    for run in runs:
        if all(summary_path(run, kind).exists() for kind in SUMMARIES):
            tables = {kind: pq.read_table(summary_path(run, kind)) for kind in SUMMARIES}
            if all((t.schema.metadata or {}).get(_DIGEST_KEY) == summary_digest() for t in tables.values()):
                summaries[run] = tables
    cells = {run: _cell(summaries[run]["table"]) if run in summaries else _run_cell(run) for run in runs}
    runs_of = Counter(cells.values())
    lone = [run for run in runs if run in summaries and runs_of[cells[run]] == 1]
    pieces = [{kind: table.to_pandas() for kind, table in summaries[run].items()} for run in lone]
    rest = [run for run in runs if run not in lone]
    if rest:
        pieces.append(cell_tables(*load(rest, n_jobs), n_jobs))
    keys = {"roc": CELL, "auc": CELL, "table": CELL + ["tau"], "timing": CELL + ["tau"]}
    # Stable: the ROC points keep their order within a cell.
    return {kind: _concat([p[kind] for p in pieces]).sort_values(keys[kind], kind="stable", ignore_index=True)
            for kind in SUMMARIES}


def _concat(frames: list[pd.DataFrame]) -> pd.DataFrame:
    filled = [f for f in frames if not f.empty]  # baselines' empty ROC tables carry no dtypes
    return pd.concat(filled, ignore_index=True) if filled else frames[0]


def _run_cell(run: Path) -> tuple:
    """A run's cell from the first row of its trials (columns it predates at their defaults)."""
    import pyarrow.parquet as pq

    file = pq.ParquetFile(run / "trials.parquet")
    present = [c for c in CELL if c in file.schema_arrow.names]
    return _cell(_with_later_columns(file.read_row_group(0, columns=present).slice(0, 1)))


def _sample(fpr, tpr, thr):
    idx = np.searchsorted(fpr, PFA_GRID, side="right") - 1
    rise = np.flatnonzero(fpr == 0)  # keep the whole P_FA = 0 segment's top
    keep = np.unique(np.r_[idx[idx >= 0], rise[-1:], fpr.size - 1])
    return fpr[keep], tpr[keep], thr[keep]


def roc_tables(pairs: dict[tuple, pd.DataFrame], n_jobs: int = 1) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Sampled ROC curve and AUC summary of every cell (``pairs`` as from ``load``)."""
    cells = [(cell, g) for cell, g in pairs.items() if not g.empty]  # baselines have no scores
    if not cells:
        return pd.DataFrame(columns=CELL + ["p_fa", "p_d", "log_tau"]), pd.DataFrame(columns=CELL + ["auc"])
    done = joblib.Parallel(n_jobs=n_jobs, prefer="threads")(joblib.delayed(_roc)(cell, g) for cell, g in cells)
    return pd.concat([roc for roc, _ in done], ignore_index=True), pd.DataFrame([row for _, row in done])


def _roc(cell: tuple, g: pd.DataFrame) -> tuple[pd.DataFrame, dict]:
    label, score = g["label"].to_numpy(), g["score"].to_numpy()
    fpr, tpr, thr = metrics.roc_curve(label, score)
    head = dict(zip(CELL, cell))
    f, t, th = _sample(fpr, tpr, thr)
    return pd.DataFrame({**head, "p_fa": f, "p_d": t, "log_tau": th}), {
        **head,
        "auc": metrics.auc(fpr, tpr),
        "p_d_at_zero_fa": float(tpr[fpr == 0].max()),
        "n_trials": int(np.unique(g["seed"].to_numpy(np.int64) * (1 << 32) + g["trial"].to_numpy(np.int64)).size),
        "n_pairs": len(g),
        "n_true": int(label.sum()),
        "n_order_flips": int((label & ~g["order_consistent"].to_numpy()).sum()),
    }


def ratio(num, den):
    """num / den, NaN where den is 0 (counts: a rate with no cases is unknown, not 0)."""
    return np.where(den > 0, num / np.maximum(den, 1), np.nan)


def summary_table(trials: pd.DataFrame) -> pd.DataFrame:
    keys = CELL + ["tau"]
    # Every per-trial quantity is a column, so one grouping (the costly part) serves all.
    trials = trials.assign(has_fp=trials["fp"] > 0, rmse_over_sigma=trials["rmse"] / trials["sigma"])
    g = trials.groupby(keys, sort=True)
    t = g[["tp", "fp", "md", "tn", "common", "unpaired", "wrong_pairs", "duplicates"]].sum()
    t.insert(0, "n_trials", g.size())
    t["precision"] = ratio(t.tp, t.tp + t.fp)
    t["md_rate"] = ratio(t.md, t.tp + t.md)
    t["p_d"] = ratio(t.tp, t.tp + t.md)
    t["p_fa"] = ratio(t.fp, t.fp + t.tn)
    t["recall_common"] = ratio(t.tp, t.common)
    t["trials_with_fp"] = g["has_fp"].sum()
    lm = g[["correct_pairs", "wrong_pairs", "n_common_landmarks"]].sum()
    t["landmark_precision"] = ratio(lm.correct_pairs, lm.correct_pairs + lm.wrong_pairs)
    t["landmark_recall"] = ratio(lm.correct_pairs, lm.n_common_landmarks)
    t["false_merge_rate"] = g["false_merge"].mean()
    t["matched_rate"] = g["matched"].mean()
    t["success_rate"] = g["success"].mean()
    t["median_rot_err_deg"] = g["rot_err_deg"].median()
    t["median_rmse_over_sigma"] = g["rmse_over_sigma"].median()
    t["mean_log_tau"] = g["log_tau"].mean()
    # Triangles declared by the GLRT test alone (consensus also declares those its association implies).
    t["recall_glrt"] = ratio(t.tp - g["tp_implied"].sum(), t.common)
    t["found_rate"] = g["transform_found"].mean()
    t["correct_per_trial"] = g["correct_pairs"].mean()
    t["wrong_per_trial"] = g["wrong_pairs"].mean()
    # Two oracles: "oracle" knows the true transform and the true prior π, "transform_oracle" the
    # transform only (it estimates π as consensus does).
    for name in ("oracle", "transform_oracle"):
        if f"{name}_correct_pairs" not in trials:
            continue
        correct, wrong = f"{name}_correct_pairs", f"{name}_wrong_pairs"
        oracle = g[[correct, wrong]].sum()
        t[f"{name}_correct_per_trial"] = g[correct].mean()
        t[f"{name}_wrong_per_trial"] = g[wrong].mean()
        t[f"correct_vs_{name}"] = ratio(lm.correct_pairs, oracle[correct])
        t[f"wrong_vs_{name}"] = ratio(lm.wrong_pairs, oracle[wrong])
        # The same on the trials whose transform was found: below about 15 dB even the oracle pairs
        # few landmarks, so association is judged apart from whether the transform was found.
        found = trials[["correct_pairs", "wrong_pairs", correct, wrong]].where(
            trials["transform_found"].astype(bool), 0).groupby([trials[k] for k in keys]).sum()
        t[f"correct_vs_{name}_found"] = ratio(found.correct_pairs, found[correct])
        t[f"wrong_vs_{name}_found"] = ratio(found.wrong_pairs, found[wrong])
    return t.reset_index()


def timing_table(trials: pd.DataFrame) -> pd.DataFrame:
    """Median time per merge (ms) per cell and τ rule: kept out of table.csv,
    which is then reproducible to the bit."""
    keys = CELL + ["tau"]
    ms = 1e3 * (trials["time_match_s"] + trials["time_merge_s"])
    return ms.groupby([trials[k] for k in keys]).median().rename("median_ms_per_merge").reset_index()


def aggregate(dirs, out, n_jobs: int = 1) -> dict[str, Path]:
    """Write roc.csv, auc.csv, table.csv, timing.csv and table.md into ``out`` (``n_jobs`` threads)."""
    tables = aggregate_tables(find_runs(dirs), n_jobs)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths = {name: out / f"{name}.csv" for name in SUMMARIES}
    for name in SUMMARIES:
        tables[name].to_csv(paths[name], index=False, float_format="%.4g" if name == "timing" else "%.6g")
    paths["table_md"] = out / "table.md"
    paths["table_md"].write_text(markdown_table(tables["table"]) + "\n")
    for name, examples in load_examples(dirs).items():
        plural = name.replace("example_", "examples_")
        paths[plural] = out / f"{plural}.csv"
        examples.to_csv(paths[plural], index=False, float_format="%.10g")
    return paths


def with_timing(path: Path) -> pd.DataFrame:
    """A sweep's table with its median times (NaN where timing.csv, which git does not keep, is missing);
    tables written before a scenario column existed read at its first-release value."""
    table = with_defaults(pd.read_csv(path))
    timing = path.with_name("timing.csv")
    if not timing.exists():
        return table.assign(median_ms_per_merge=float("nan"))
    return table.merge(with_defaults(pd.read_csv(timing)), on=CELL + ["tau"])


def save_table(table: pd.DataFrame, stem: Path) -> list[Path]:
    """Write ``stem.csv`` and ``stem.md`` (a Markdown table) side by side."""
    csv, md = stem.with_suffix(".csv"), stem.with_suffix(".md")
    table.to_csv(csv, index=False, float_format="%.6g")
    md.write_text(markdown(table))
    return [csv, md]


def markdown(table: pd.DataFrame) -> str:
    """A Markdown table, 3 significant digits; NaN (no match, nothing to count) as "n/a"."""
    return table.astype(object).where(table.notna(), None).to_markdown(
        index=False, floatfmt=".3g", missingval="n/a") + "\n"


def markdown_table(table: pd.DataFrame) -> str:
    cols = ["n_landmarks", "overlap", "snr_db", "unrelated", "method", "objective", "tau", "n_trials", "tp", "fp", "md",
            "precision", "md_rate", "p_d", "p_fa", "recall_common", "success_rate", "median_rmse_over_sigma"]
    return table[cols].to_markdown(index=False, floatfmt=".3g")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dirs", nargs="+", help="run or sweep directories")
    parser.add_argument("--out", required=True, help="directory for the tables")
    parser.add_argument("--n-jobs", type=int, default=2, help="reader threads (default 2)")
    args = parser.parse_args(argv)
    try:
        paths = aggregate(args.dirs, args.out, args.n_jobs)
    except (ValueError, FileNotFoundError) as exc:
        parser.exit(2, f"error: {exc}\n")
    for name, path in paths.items():
        print(f"{name}: {path}")


if __name__ == "__main__":
    main()

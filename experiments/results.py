"""One results table across every run: the results store.

    python -m experiments.results                                  # every row, the columns that vary
    python -m experiments.results --where "scenario.snr_db == 15" --columns matcher.method,tau,found_rate
    python -m experiments.results --where "matcher.method == 'consensus'" --out consensus.csv

Every run of ``python -m experiments.run`` (alone or in a sweep) writes its
cell's summary, one row per τ rule, to ``results.parquet`` in its
directory and to the store, ``<output_root>/results/``, a Parquet dataset
of one file per run directory (a rerun of a directory replaces its file).
A row holds every config value as a column (``scenario.snr_db``,
``matcher.method``, ``mc.n_trials``, ...; the τ rule list as JSON), the
rule (``tau``), the metrics of ``experiments.aggregate``'s tables
(``found_rate``, ``success_rate``, ``p_d``, ``p_fa``, ``auc``,
``median_ms_per_merge``, ...), 95 % intervals of the rates and ratios
(``<metric>_low`` / ``<metric>_high``: Wilson for rates over trials, the
delta method over trials for pooled ratios; ``experiments.intervals``),
and ``code_version``, ``run_dir``, ``run_key`` and ``written`` (UTC).
Every file has the same columns (NaN where a run has no such metric), so
``pandas.read_parquet(DIR)`` reads the dataset whole; DuckDB reads it as
``read_parquet('DIR/*.parquet')``.

``--where`` is a ``pandas.DataFrame.query`` expression; dotted column names
are quoted for it (``scenario.snr_db == 15`` works as written).
"""

from __future__ import annotations

import argparse
import datetime
import hashlib
import json
import re
from pathlib import Path

import numpy as np
import pandas as pd

#: The store's directory below ``output_root``.
STORE = "results"
#: A run's own rows, beside its trials.
RUN_FILE = "results.parquet"
#: Rates over trials (metric -> per-trial 0/1 column of trials.parquet): Wilson intervals.
RATES = {"found_rate": "transform_found", "success_rate": "success", "false_merge_rate": "false_merge",
         "matched_rate": "matched"}
#: Ratios of sums over trials (metric -> numerator, denominator terms): delta-method intervals over trials.
RATIOS = {"p_d": ("tp", ("tp", "md")), "p_fa": ("fp", ("fp", "tn")), "precision": ("tp", ("tp", "fp")),
          "md_rate": ("md", ("tp", "md")), "landmark_precision": ("correct_pairs", ("correct_pairs", "wrong_pairs")),
          "landmark_recall": ("correct_pairs", ("n_common_landmarks",))}
#: Columns of the optional oracle associations (``matcher.oracle``), NaN in runs without them.
ORACLE_COLUMNS = [f"{p}{name}{s}" for name in ("oracle", "transform_oracle")
                  for p, s in (("", "_correct_per_trial"), ("", "_wrong_per_trial"), ("correct_vs_", ""),
                               ("wrong_vs_", ""), ("correct_vs_", "_found"), ("wrong_vs_", "_found"))]
#: ROC summary columns (triangle-LP methods only; NaN for the baselines).
AUC_COLUMNS = {"auc": "float64", "p_d_at_zero_fa": "float64", "n_pairs": "Int64", "n_true": "Int64",
               "n_order_flips": "Int64"}
#: Shown by default, after the config columns that vary.
SHOWN = ["tau", "n_trials", "found_rate", "success_rate", "false_merge_rate", "p_d", "p_fa", "auc",
         "median_ms_per_merge"]


def config_columns(cfg) -> dict:
    """Every value of a composed config as ``{dotted key: value}`` (lists as JSON, choices by name)."""
    from omegaconf import OmegaConf

    plain = OmegaConf.to_container(cfg, resolve=True, enum_to_str=True)
    plain.pop("hydra", None)
    out = {}

    def walk(node, prefix):
        for key, value in node.items():
            if isinstance(value, dict):
                walk(value, f"{prefix}{key}.")
            else:
                out[f"{prefix}{key}"] = json.dumps(value) if isinstance(value, list) else value

    walk(plain, "")
    return out


def run_rows(cfg, run_dir, trials: pd.DataFrame, tables: dict[str, pd.DataFrame], run_key: str) -> pd.DataFrame:
    """A run's rows of the store: one per τ rule.

    Parameters
    ----------
    cfg : DictConfig
        The run's config.
    run_dir : path
        Its directory (recorded as ``run_dir``).
    trials : DataFrame
        Its trials (``trials.parquet``'s rows).
    tables : dict
        Its ``table``, ``auc`` and ``timing`` summaries (``aggregate.run_summaries``), as DataFrames.
    run_key : str
        Its trial-cache key.

    Returns
    -------
    DataFrame
        Config columns, ``tau``, the metrics and their intervals, ``code_version``, ``run_dir``,
        ``run_key``, ``written``.
    """
    import mapmerge

    from .aggregate import CELL
    from .intervals import ratio_interval, wilson
    from .trials import code_digest

    table = tables["table"].drop(columns=CELL)
    auc = tables["auc"].drop(columns=CELL + ["n_trials"], errors="ignore")
    rows = table.merge(tables["timing"].drop(columns=CELL), on="tau", how="left")
    for col, dtype in AUC_COLUMNS.items():
        rows[col] = (auc[col].iloc[0] if col in auc and len(auc) else np.nan)
        rows[col] = rows[col].astype(dtype)
    for col in ORACLE_COLUMNS:
        if col not in rows:
            rows[col] = np.nan
    for metric in RATES:
        rows[f"{metric}_low"], rows[f"{metric}_high"] = wilson(np.round(rows[metric] * rows.n_trials), rows.n_trials)
    by_rule = {rule: t for rule, t in trials.groupby("tau", sort=False)}
    for metric, (num, den) in RATIOS.items():
        bounds = [ratio_interval(by_rule[rule][num], sum(by_rule[rule][d] for d in den)) for rule in rows.tau]
        rows[f"{metric}_low"], rows[f"{metric}_high"] = np.array(bounds, float).reshape(-1, 2).T
    config = config_columns(cfg)
    head = pd.DataFrame({key: [value] * len(rows) for key, value in config.items()})
    # None-valued keys (mc.address, aggregate_dir) are optional strings: typed so every file agrees.
    for key, value in config.items():
        if value is None:
            head[key] = head[key].astype("string")
    meta = pd.DataFrame({
        "code_version": f"{mapmerge.__version__}+{code_digest()[:12]}",
        "run_dir": str(Path(run_dir).resolve()),
        "run_key": run_key,
        "written": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
    }, index=rows.index)
    return pd.concat([head, rows, meta], axis=1)


def store_file(store, run_dir) -> Path:
    """A run directory's file in the store (one per directory: a rerun replaces it)."""
    name = hashlib.sha256(str(Path(run_dir).resolve()).encode()).hexdigest()[:16]
    return Path(store) / f"{name}.parquet"


def load(source="outputs") -> pd.DataFrame:
    """The results rows of a store, a sweep or run directory, or one Parquet file.

    Parameters
    ----------
    source : path
        An output root (its ``results/`` store), a store directory, a sweep or run directory (its
        runs' ``results.parquet``) or a Parquet file.

    Returns
    -------
    DataFrame
        One row per run, cell and τ rule, oldest first.

    Raises
    ------
    FileNotFoundError
        When ``source`` holds no results.
    """
    source = Path(source)
    if source.is_file():
        files = [source]
    elif (source / STORE).is_dir() and not list(source.glob(f"*/{RUN_FILE}")):
        files = sorted((source / STORE).glob("*.parquet"))
    elif list(source.glob("*.parquet")) and not (source / RUN_FILE).exists():
        files = sorted(source.glob("*.parquet"))
    else:
        files = sorted(source.rglob(RUN_FILE))
    if not files:
        raise FileNotFoundError(f"no results below {source}: expected {STORE}/*.parquet (an output root) "
                                f"or {RUN_FILE} files (a sweep or run directory)")
    frames = [pd.read_parquet(f) for f in files]
    return pd.concat(frames, ignore_index=True).sort_values("written", kind="stable", ignore_index=True)


def quoted(expr: str, columns) -> str:
    """``expr`` with the dotted column names it uses back-quoted, as ``DataFrame.query`` needs them."""
    for col in sorted((c for c in columns if "." in c), key=len, reverse=True):
        expr = re.sub(rf"(?<![`\w.]){re.escape(col)}(?![\w`])", f"`{col}`", expr)
    return expr


def select(rows: pd.DataFrame, where: str | None) -> pd.DataFrame:
    """The rows where ``where`` (a ``DataFrame.query`` expression, dotted names unquoted) holds.

    Raises
    ------
    ValueError
        When ``where`` is not a valid expression over the table's columns.
    """
    if not where:
        return rows
    try:
        return rows.query(quoted(where, rows.columns))
    except (SyntaxError, pd.errors.UndefinedVariableError, KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"--where {where!r} is invalid: {' '.join(str(exc).split())}") from None


def varying(rows: pd.DataFrame) -> list[str]:
    """The config columns (``scenario.``, ``matcher.``, ``mc.``, ``name``) whose value differs between rows."""
    cols = [c for c in rows.columns if c.split(".")[0] in ("scenario", "matcher", "mc", "name")]
    return [c for c in cols if rows[c].astype(str).nunique() > 1]


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("source", nargs="?", default="outputs",
                        help="an output root (default outputs), a store, sweep or run directory, or a file")
    parser.add_argument("--where", help="a pandas query, e.g. \"scenario.snr_db == 15 and tau != 'oracle'\"")
    parser.add_argument("--columns", help="comma-separated columns to print (default: the config columns that "
                        "vary, then " + ", ".join(SHOWN) + ")")
    parser.add_argument("--out", help="write every column of the selected rows to this .csv or .parquet file")
    args = parser.parse_args(argv)
    try:
        rows = select(load(args.source), args.where)
        if args.columns:
            shown = args.columns.split(",")
            unknown = [c for c in shown if c not in rows.columns]
            if unknown:
                raise ValueError(f"--columns: no column {unknown[0]!r}; the table has {', '.join(rows.columns)}")
        else:
            shown = [c for c in varying(rows) + SHOWN if c in rows.columns]
        if args.out and not args.out.endswith((".csv", ".parquet")):
            raise ValueError(f"--out {args.out!r} is invalid: must end in .csv or .parquet")
    except (ValueError, FileNotFoundError) as exc:
        parser.exit(2, f"error: {exc}\n")
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        if args.out.endswith(".csv"):
            rows.to_csv(args.out, index=False)
        else:
            rows.to_parquet(args.out, index=False)
        print(f"{len(rows)} rows -> {args.out}")
        return
    from .aggregate import markdown

    print(markdown(rows[shown]) if len(rows) else "no rows")


if __name__ == "__main__":
    main()

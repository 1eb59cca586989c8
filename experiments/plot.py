"""A figure of any sweep: any metric against any swept parameter, faceted.

    python -m experiments.plot outputs/sweeps/mine --x scenario.snr_db --y found_rate \\
        --hue matcher.method --col scenario.n_landmarks -o fig.png
    python -m experiments.plot outputs --where "matcher.method == 'consensus'" --x scenario.overlap \\
        --y success_rate --col scenario.snr_db -o overlap.png      # from the results store
    python -m experiments.plot outputs/sweeps/mine --kind roc -o roc.png   # ROC panels, wrapped

SOURCE is a sweep or run directory (its runs' ``results.parquet``) or an
output root / results store (``experiments.results``). ``--y`` is any
metric column of the results table, ``--x``, ``--hue``, ``--col`` and
``--row`` any config column (``snr_db`` stands for ``scenario.snr_db``
when unambiguous) or ``tau``. The panels wrap onto rows (``--wrap``
columns at most) when only ``--col`` is given. A metric with a 95 %
interval in the table (``<y>_low`` / ``<y>_high``) gets a shaded band.

Every other config value that varies between the rows must be pinned with
``--where`` or mapped to a facet: the figure never averages over, or
silently drops, a dimension. The one exception is ``scenario.unrelated``:
related and unrelated map pairs are drawn on rows of their own (on
unrelated pairs a found transform is a false merge). The τ rule, unless
mapped, is ``--tau`` (default ``chi2:0.01``, the calibrated rule; methods
without τ have ``none``). Of several runs of one setting (the same cell at
100 and 200 trials), the one with the most trials is drawn.

``--kind roc`` draws the ROC curves of a sweep directory (from its trials,
or of an aggregate directory's ``roc.csv``), one panel per scenario and
matcher wrapped onto rows; unrelated-map cells, which have no true pairs
and so no ROC curve, are named on stderr.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import pandas as pd  # noqa: E402

from .figures import CALIBRATED_RULE, STYLE, fig3, legend_entries, related_cells  # noqa: E402
from .results import load, select, varying  # noqa: E402

#: Axis labels, with units, of the usual columns (others are labelled by name).
LABELS = {
    "scenario.snr_db": "SNR (dB)",
    "scenario.n_landmarks": "landmarks per map",
    "scenario.overlap": "overlap (fraction of landmarks common)",
    "scenario.aspect": "map aspect ratio",
    "scenario.p_detect": "detection probability (interleaved layout)",
    "scenario.clutter": "clutter (spurious landmarks per landmark)",
    "scenario.anisotropy": "noise anisotropy",
    "scenario.layout": "layout",
    "scenario.unrelated": "map pair",
    "matcher.method": "method",
    "matcher.objective": "LP objective",
    "mc.seed": "seed",
    "tau": "τ rule",
    "found_rate": "transform found (fraction of trials)",
    "success_rate": "merge success (fraction of trials)",
    "false_merge_rate": "false merges (fraction of trials)",
    "matched_rate": "matched (fraction of trials)",
    "p_d": "probability of detection $P_D$",
    "p_fa": "probability of false alarm $P_{FA}$",
    "precision": "precision of declared triangle pairs",
    "md_rate": "missed-detection rate",
    "auc": "area under the ROC curve",
    "p_d_at_zero_fa": "$P_D$ at zero false alarms",
    "landmark_precision": "landmark pairs correct (fraction)",
    "landmark_recall": "common landmarks paired correctly (fraction)",
    "median_rot_err_deg": "median rotation error (deg)",
    "median_rmse_over_sigma": "median combined-map RMSE (σ)",
    "median_ms_per_merge": "median time per merge (ms)",
    "correct_per_trial": "correct landmark pairs per trial",
    "wrong_per_trial": "wrong landmark pairs per trial",
    "mean_log_tau": "mean log τ",
}
#: Config columns that do not change the numbers (or are drawn apart: the run with most trials wins).
IGNORED = {"name", "aggregate_dir", "output_root", "matcher.taus", "matcher.oracle", "mc.n_trials", "mc.n_jobs",
           "mc.chunk_size", "mc.backend", "mc.address", "mc.progress", "mc.examples"}
#: Panels side by side at most, before they wrap onto another row.
WRAP = 4
#: Inches per panel (width, height).
PANEL = (2.6, 2.2)


def label(column: str) -> str:
    return LABELS.get(column, column)


def value_text(column: str, value) -> str:
    if column == "scenario.unrelated":
        return "unrelated maps" if bool(value) else "related maps"
    if column == "scenario.overlap":
        return f"{float(value):.0%} overlap"
    if column == "scenario.n_landmarks":
        return f"{int(value)} landmarks"
    if column == "scenario.snr_db":
        return f"{float(value):g} dB"
    if column == "scenario.layout":
        return f"{value} layout"
    return f"{label(column)} {value:g}" if isinstance(value, float) else f"{label(column)} {value}"


def resolve(name: str | None, columns, what: str) -> str | None:
    """A column named in full or by its last part (``snr_db`` for ``scenario.snr_db``).

    Raises
    ------
    ValueError
        When no column, or more than one, has that name.
    """
    if name is None or name in columns:
        return name
    matches = [c for c in columns if c.rsplit(".", 1)[-1] == name]
    if len(matches) == 1:
        return matches[0]
    known = ", ".join(c for c in columns if "." in c or c == "tau")
    raise ValueError(f"{what}={name!r} is invalid: " + (f"ambiguous ({', '.join(matches)})" if matches
                                                         else f"no such column; config columns: {known}"))


def prepare(rows: pd.DataFrame, x: str, y: str, hue: str | None, col: str | None, row: str | None,
            tau: str | None) -> tuple[pd.DataFrame, str | None, list[str]]:
    """The rows to draw, the row facet (``scenario.unrelated`` added when it varies) and notes for the caption.

    Raises
    ------
    ValueError
        When a varying config value is neither mapped nor pinned, when ``y`` is not a metric
        column, or when no row is left.
    """
    if y not in rows or not pd.api.types.is_numeric_dtype(rows[y]):
        raise ValueError(f"--y={y!r} is invalid: not a numeric column of the results table")
    notes = []
    mapped = {x, hue, col, row} - {None}
    if "tau" not in mapped:
        rules = sorted(set(rows.tau) - {"none"})
        pick = tau or (CALIBRATED_RULE if CALIBRATED_RULE in rules or not rules else None)
        if pick is None:
            raise ValueError(f"the rows hold the τ rules {', '.join(rules)}: pick one with --tau or map tau "
                             "to --hue / --col / --row")
        rows = rows[rows.tau.isin([pick, "none"])]
        notes.append(f"τ rule {pick}" + (" (methods without τ: none)" if "none" in set(rows.tau) else ""))
    # Of runs of one setting, the one with the most trials (then the latest).
    keys = [c for c in rows.columns if c.split(".")[0] in ("scenario", "matcher", "mc") and c not in IGNORED]
    keys.append("tau")
    n_before = len(rows)
    rows = rows.sort_values(["n_trials", "written"], kind="stable").drop_duplicates(keys, keep="last")
    if len(rows) < n_before:
        print(f"note: {n_before - len(rows)} row(s) of settings run more than once: the run with the most "
              "trials is drawn", file=sys.stderr)
    free = [c for c in varying(rows) if c not in IGNORED and c not in mapped]
    if "scenario.unrelated" in free and row is None:
        row = "scenario.unrelated"
        free.remove(row)
        print("note: related and unrelated map pairs drawn on rows of their own", file=sys.stderr)
    if free:
        values = ", ".join(sorted(rows[free[0]].astype(str).unique()))
        raise ValueError(f"{free[0]} takes several values ({values}): map it to --hue / --col / --row or pick "
                         f"one with --where")
    if rows.empty:
        raise ValueError("no rows to draw (check --where and --tau)")
    for c in ("scenario.overlap", "scenario.layout"):
        if c not in mapped and c in rows and rows[c].nunique() == 1:
            notes.insert(0, value_text(c, rows[c].iloc[0]))
    trials = sorted(rows.n_trials.unique())
    notes.append(f"{trials[0]:,} trials per point" if len(trials) == 1 else f"{trials[0]:,}-{trials[-1]:,} trials "
                 "per point")
    return rows, row, notes


def line_figure(rows: pd.DataFrame, x: str, y: str, hue: str | None, col: str | None, row: str | None,
                notes: list[str], wrap: int = WRAP):
    """``y`` against ``x``, one line per ``hue`` value, a panel per (``row``, ``col``) value."""
    def values(column):
        return [None] if column is None else sorted(rows[column].unique())

    cols, rws, hues = values(col), values(row), values(hue)
    panels = [(r, c) for r in rws for c in cols]
    ncols = len(cols) if row is not None else min(len(cols), wrap)
    nrows = -(-len(panels) // ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(PANEL[0] * ncols + 0.3, PANEL[1] * nrows + 0.5),
                             sharex=True, sharey=True, squeeze=False)
    cmap = plt.get_cmap("tab10")
    colours = {h: cmap(i % 10) for i, h in enumerate(hues)}
    markers = dict(zip(hues, "osD^vPX*<>" * 3))
    numeric_x = pd.api.types.is_numeric_dtype(rows[x])
    band = f"{y}_low" in rows and rows[f"{y}_low"].notna().any()
    for k, (r, c) in enumerate(panels):
        ax = axes[k // ncols, k % ncols]
        panel = rows
        if r is not None:
            panel = panel[panel[row] == r]
        if c is not None:
            panel = panel[panel[col] == c]
        for h in hues:
            line = (panel if h is None else panel[panel[hue] == h]).sort_values(x)
            if line.empty:
                continue
            xs = line[x].to_numpy() if numeric_x else line[x].astype(str).to_numpy()
            ax.plot(xs, line[y], marker=markers[h], ms=3, color=colours[h], label=None if h is None else str(h))
            if band:
                ax.fill_between(xs, line[f"{y}_low"], line[f"{y}_high"], color=colours[h], alpha=0.18, lw=0)
        ax.set_title(", ".join(value_text(k_, v) for k_, v in ((row, r), (col, c)) if k_ is not None))
        ax.grid(alpha=0.3, lw=0.4)
    for k in range(len(panels), nrows * ncols):
        axes[k // ncols, k % ncols].set_visible(False)
    if y.endswith("_rate") or y in ("p_d", "p_fa", "precision", "auc", "p_d_at_zero_fa") or y.startswith("landmark_"):
        axes[0, 0].set_ylim(-0.02, 1.02)
    for ax in axes[:, 0]:
        ax.set_ylabel(label(y))
    for k in range(len(panels)):
        # The lowest panel of each column (the last band may be short) carries the x label.
        if k + ncols >= len(panels):
            axes[k // ncols, k % ncols].set_xlabel(label(x))
            axes[k // ncols, k % ncols].tick_params(labelbottom=True)
    if band:
        notes.append("shaded: 95 % confidence interval")
    fig.suptitle("; ".join(notes), fontsize=7)
    handles, labels = legend_entries(axes)  # a hue value absent from the first panel still gets its entry
    fig.tight_layout()
    if hue is not None:
        fig.legend(handles, labels, title=label(hue), loc="upper left", bbox_to_anchor=(1.0, 0.95), frameon=False)
    return fig


def roc_figure(source: Path, out: Path, wrap: int) -> list[Path]:
    """ROC panels of a sweep (from its trials) or an aggregate directory, wrapped; unrelated cells named."""
    from .aggregate import aggregate_tables, find_runs

    if (source / "roc.csv").exists():
        tables = {kind: pd.read_csv(source / f"{kind}.csv") for kind in ("roc", "auc", "table")}
    else:
        tables = aggregate_tables(find_runs([source]))
    related = related_cells(tables)
    if related["roc"].empty:
        raise ValueError(f"no ROC curve in {source}: its cells are unrelated maps or methods without scores")
    with plt.rc_context(STYLE):
        return fig3(related["roc"], related["auc"], out.parent, out.stem, table=related["table"], wrap=wrap)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("source", help="a sweep or run directory, or an output root / results store")
    parser.add_argument("--kind", choices=("line", "roc"), default="line",
                        help="line: --y against --x (default); roc: the ROC panels of a sweep")
    parser.add_argument("--x", help="config column on the x axis, e.g. scenario.snr_db")
    parser.add_argument("--y", default="found_rate", help="metric column (default found_rate)")
    parser.add_argument("--hue", help="config column drawn as one line per value, e.g. matcher.method")
    parser.add_argument("--col", help="config column: one panel per value, wrapping onto rows")
    parser.add_argument("--row", help="config column: one row of panels per value")
    parser.add_argument("--where", help="pandas query selecting rows, e.g. \"scenario.overlap == 0.75\"")
    parser.add_argument("--tau", help=f"τ rule drawn when tau is not mapped (default {CALIBRATED_RULE})")
    parser.add_argument("--wrap", type=int, default=WRAP, help=f"panels side by side at most (default {WRAP})")
    parser.add_argument("-o", "--out", required=True, help="the figure (.png; a .pdf is written beside it)")
    args = parser.parse_args(argv)
    out = Path(args.out)
    try:
        if args.wrap < 1:
            raise ValueError(f"--wrap={args.wrap} is invalid: must be >= 1")
        if out.suffix != ".png":
            raise ValueError(f"-o {args.out!r} is invalid: must end in .png")
        out.parent.mkdir(parents=True, exist_ok=True)
        if args.kind == "roc":
            made = roc_figure(Path(args.source), out, args.wrap)
        else:
            rows = select(load(args.source), args.where)
            if args.x is None:
                raise ValueError("--x is required with --kind line (e.g. --x scenario.snr_db)")
            x, hue, col, row = (resolve(getattr(args, k), rows.columns, f"--{k}") for k in ("x", "hue", "col", "row"))
            y = resolve(args.y, rows.columns, "--y")
            rows, row, notes = prepare(rows, x, y, hue, col, row, args.tau)
            with plt.rc_context(STYLE):
                fig = line_figure(rows, x, y, hue, col, row, notes, args.wrap)
                made = [out, out.with_suffix(".pdf")]
                fig.savefig(made[0], bbox_inches="tight", metadata={"Software": None})
                fig.savefig(made[1], bbox_inches="tight", metadata={"CreationDate": None, "Creator": None,
                                                                    "Producer": None})
                plt.close(fig)
    except (ValueError, FileNotFoundError) as exc:
        parser.exit(2, f"error: {exc}\n")
    for path in made:
        print(path)


if __name__ == "__main__":
    main()

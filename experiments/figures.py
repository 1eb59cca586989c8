"""Figures drawn from aggregated tables only.

    python -m experiments.figures RESULTS_DIR      # the paper's Fig. 1-3 (make paper's layout)
    python -m experiments.figures SWEEP/aggregate  # the ROC curves of any aggregate

For the paper's layout, looks for ``fig3/roc.csv`` + ``fig3/auc.csv`` (Fig. 3,
ROC curves), ``fig1/examples_triangles.csv`` (Fig. 1, detections on both
maps) and ``fig2/examples_landmarks.csv`` (Fig. 2, combined map vs ground
truth) below RESULTS_DIR and writes ``fig1``/``fig2``/``fig3`` as PNG and
PDF there. A directory holding ``roc.csv`` itself (any sweep's aggregate)
gets ``roc.png``/``roc.pdf``: one panel per scenario and matcher (four
side by side, then wrapping onto further rows), one curve per SNR, and its
``table.md`` is printed; unrelated-map cells (no ROC curve) are named.
``python -m experiments.plot`` draws any metric of any sweep.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from matplotlib.collections import PolyCollection  # noqa: E402

STYLE = {
    "font.size": 8,
    "axes.titlesize": 8,
    "axes.labelsize": 8,
    "legend.fontsize": 6.5,
    "xtick.labelsize": 7,
    "ytick.labelsize": 7,
    "lines.linewidth": 1.0,
    "savefig.dpi": 200,
}
#: Detection colours of the paper's Fig. 1 (green TP, blue MD, red FP).
STATUS_COLOURS = {"tp": "tab:green", "md": "tab:blue", "fp": "tab:red"}
#: Fig. 3 panel order of the paper: (landmarks, overlap).
FIG3_PANELS = [(10, 0.75), (10, 0.5), (20, 0.75), (20, 0.5)]


def save_figure(fig, out: Path, name: str) -> list[Path]:
    """Write ``fig`` as ``out/name.png`` and ``.pdf`` with no timestamps or software versions in their
    metadata (so that a rerun gives the same bytes), and close it."""
    paths = [out / f"{name}.png", out / f"{name}.pdf"]
    fig.savefig(paths[0], metadata={"Software": None})
    fig.savefig(paths[1], metadata={"CreationDate": None, "Creator": None, "Producer": None})
    plt.close(fig)
    return paths


def legend_entries(axes) -> tuple[list, list]:
    """Every labelled line of every panel, once (the first panel's first): handles and labels for one legend
    of the whole figure."""
    named = {}
    for ax in np.ravel(axes):
        for handle, label in zip(*ax.get_legend_handles_labels()):
            named.setdefault(label, handle)
    return list(named.values()), list(named)


#: The calibrated τ rule marked on the Fig. 3 curves.
CALIBRATED_RULE = "chi2:0.01"


def fig3(roc: pd.DataFrame, auc: pd.DataFrame, out: Path, name: str = "fig3",
         table: pd.DataFrame | None = None, wrap: int | None = None) -> list[Path]:
    """Monte Carlo ROC curves, one column per panel, one curve per SNR.

    Panels are the (landmarks, overlap, method, objective) combinations in
    the tables, in the paper's order where they are the paper's. The top
    row is the paper's linear plot; the bottom row repeats it with P_FA on
    a log scale, where the curves crowd the corner. With ``table``, the
    (P_FA, P_D) that the calibrated χ²₃ rule achieved is marked on each
    curve. With ``wrap``, at most that many panels side by side: the rest
    continue on further pairs of rows.
    """
    keys = ["n_landmarks", "overlap", "method", "objective"]
    panels = roc[keys].drop_duplicates().itertuples(index=False, name=None)
    order = {p: k for k, p in enumerate(FIG3_PANELS)}
    panels = sorted(panels, key=lambda p: (order.get((p[0], p[1]), len(order)), p))
    several = len({p[2:] for p in panels}) > 1
    snrs = sorted(roc["snr_db"].unique())
    cmap = plt.get_cmap("viridis")
    colours = {s: cmap(i / max(len(snrs) - 1, 1)) for i, s in enumerate(snrs)}
    ncols = len(panels) if wrap is None else min(len(panels), wrap)
    bands = -(-len(panels) // ncols)
    fig, grid = plt.subplots(2 * bands, ncols, figsize=(2.6 * ncols + 0.4, 5.6 * bands), sharey=True,
                             squeeze=False)
    for i, (n, ov, method, objective) in enumerate(panels):
        letter = chr(ord("a") + i) if i < 26 else str(i + 1)
        axes, col = grid[2 * (i // ncols):2 * (i // ncols) + 2], i % ncols
        sel = {k: v for k, v in zip(keys, (n, ov, method, objective))}

        def rows(df):
            mask = np.isclose(df.overlap, ov) & (df.n_landmarks == n) & (df.method == method) \
                & (df.objective == objective)
            return df[mask]

        panel, panel_auc = rows(roc), rows(auc)
        for ax in axes[:, col]:
            for snr in snrs:
                curve = panel[panel.snr_db == snr]
                if curve.empty:
                    continue
                a = panel_auc[panel_auc.snr_db == snr]
                ax.step(curve.p_fa, curve.p_d, where="post", color=colours[snr],
                        label=f"{snr:g} dB (AUC {a.auc.iloc[0]:.3f})")
                if table is not None:
                    cal = rows(table)
                    cal = cal[(cal.snr_db == snr) & (cal.tau == CALIBRATED_RULE)]
                    ax.plot(cal.p_fa, cal.p_d, "o", ms=3.5, mfc="none", color=colours[snr])
            ax.set_ylim(0, 1.01)
            ax.grid(alpha=0.3, lw=0.4, which="both")
        trials = int(panel_auc.n_trials.max()) if not panel_auc.empty else 0
        title = f"({letter}) {n} landmarks, {ov:.0%} overlap"
        if several:
            title += f"\n{sel['method']}, LP objective {sel['objective']}"
        axes[0, col].set_title(f"{title}\n{trials:,} trials per curve")
        axes[0, col].plot([0, 1], [0, 1], color="0.8", lw=0.6, ls=":")
        axes[0, col].set_xlim(0, 1)
        axes[1, col].set_xscale("log")
        axes[1, col].set_xlim(1e-5, 1)
        axes[0, col].legend(loc="lower right", frameon=False, handlelength=1.2, fontsize=5.5)
        axes[0, col].set_xlabel("$P_{FA}$")
        axes[1, col].set_xlabel("$P_{FA}$ (log scale)")
    for i in range(len(panels), bands * ncols):  # the last band's empty places
        for ax in grid[2 * (i // ncols):2 * (i // ncols) + 2, i % ncols]:
            ax.set_visible(False)
    for ax in grid[:, 0]:
        ax.set_ylabel("probability of detection $P_D$")
    if table is not None:
        fig.text(0.5, 0.005, f"circles: P_FA, P_D achieved by the calibrated rule τ = {CALIBRATED_RULE} "
                 "(χ²₃ tail probability of true pairs)", ha="center", fontsize=6.5)
    fig.tight_layout(rect=(0, 0.02, 1, 1))
    return save_figure(fig, out, name)


def _triangles(ax, tri: pd.DataFrame):
    xy = tri[["x1", "y1", "x2", "y2", "x3", "y3"]].to_numpy().reshape(-1, 3, 2)
    status = tri["status"].to_numpy()
    plain = ~np.isin(status, list(STATUS_COLOURS))
    ax.add_collection(PolyCollection(xy[plain], facecolors="none", edgecolors="0.75", linewidths=0.4))
    for key, colour in STATUS_COLOURS.items():
        sel = status == key
        ax.add_collection(PolyCollection(xy[sel], facecolors=colour, edgecolors=colour,
                                         alpha=0.45, linewidths=0.6))
    ax.autoscale_view()
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])
    counts = {k: int((status == k).sum()) for k in STATUS_COLOURS}
    return counts


def fig1(triangles: pd.DataFrame, out: Path, name: str = "fig1") -> list[Path]:
    """Both maps' triangles: true detections green, missed blue, false red."""
    snrs = sorted(triangles["snr_db"].unique(), reverse=True)
    fig, axes = plt.subplots(len(snrs), 2, figsize=(6.5, 3.2 * len(snrs)), squeeze=False)
    for row, snr in zip(axes, snrs):
        cell = triangles[(triangles.snr_db == snr) & (triangles.trial == triangles.trial.min())]
        for ax, side in zip(row, ("p", "q")):
            counts = _triangles(ax, cell[cell["map"] == side])
            ax.set_title(f"{snr:g} dB, map {side}: {counts['tp']} TP (green), "
                         f"{counts['md']} MD (blue), {counts['fp']} FP (red)")
    fig.suptitle(f"Matching, {cell.n_landmarks.iloc[0]} landmarks per map, "
                 f"{cell.overlap.iloc[0]:.0%} common, τ rule: {cell.tau.iloc[0]}", fontsize=8)
    fig.tight_layout()
    return save_figure(fig, out, name)


def fig2(landmarks: pd.DataFrame, out: Path, name: str = "fig2") -> list[Path]:
    """Combined map against ground truth, duplicates (a landmark in two rows) marked."""
    snrs = sorted(landmarks["snr_db"].unique(), reverse=True)
    fig, axes = plt.subplots(1, len(snrs), figsize=(3.4 * len(snrs), 3.9), squeeze=False)
    for ax, snr in zip(axes[0], snrs):
        cell = landmarks[(landmarks.snr_db == snr) & (landmarks.trial == landmarks.trial.min())]
        truth, merged = cell[cell.kind == "truth"], cell[cell.kind == "merged"]
        twice = merged[merged.id.duplicated(keep=False)]
        ax.scatter(truth.x, truth.y, marker="+", s=30, c="k", lw=0.7, label="ground truth")
        ax.scatter(merged.x, merged.y, marker="s", s=14, facecolors="none", edgecolors="tab:red",
                   lw=0.7, label="combined map")
        ax.scatter(twice.x, twice.y, marker="s", s=14, c="tab:orange", lw=0, label="duplicate rows")
        for _, rows in twice.groupby("id"):
            ax.plot(rows.x, rows.y, color="tab:orange", lw=0.6)
        fused = int((merged.origin == "fused").sum())
        ax.set_title(f"({'ab'[list(snrs).index(snr)]}) {snr:g} dB: {len(merged)} rows, {fused} fused, "
                     f"{twice.id.nunique()} landmarks twice\nτ rule: {cell.tau.iloc[0]}"
                     + (" (ground truth: no false positive)" if cell.tau.iloc[0] == "oracle" else ""))
        ax.set_xlabel("x in map p's frame (landmark spacing = 1)")
        ax.set_ylabel("y in map p's frame")
        ax.set_aspect("equal")
        ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=3, frameon=False)
    fig.tight_layout()
    return save_figure(fig, out, name)


def draw_all(results: Path) -> list[Path]:
    """Draw every figure whose tables exist below ``results``."""
    results = Path(results)
    made = []
    with plt.rc_context(STYLE):
        if (results / "fig3" / "roc.csv").exists():
            made += fig3(pd.read_csv(results / "fig3" / "roc.csv"),
                         pd.read_csv(results / "fig3" / "auc.csv"), results,
                         table=pd.read_csv(results / "fig3" / "table.csv"))
        if (results / "fig1" / "examples_triangles.csv").exists():
            made += fig1(pd.read_csv(results / "fig1" / "examples_triangles.csv"), results)
        if (results / "fig2" / "examples_landmarks.csv").exists():
            made += fig2(pd.read_csv(results / "fig2" / "examples_landmarks.csv"), results)
    if not made:
        raise FileNotFoundError(f"no figure tables below {results}: expected fig1/, fig2/ or fig3/ "
                                "(the paper's layout) or roc.csv (an aggregate directory)")
    return made


def related_cells(tables: dict[str, pd.DataFrame]) -> dict[str, pd.DataFrame]:
    """The tables' rows of related map pairs; the unrelated-map cells, which have no true pairs and so
    no ROC curve, are named on stderr rather than dropped unseen."""
    unrelated = tables["table"][tables["table"].unrelated.astype(bool)]
    if len(unrelated):
        cells = unrelated.drop_duplicates(["n_landmarks", "overlap", "snr_db", "method"])
        print(f"note: {len(cells)} unrelated-map cell(s) have no true pairs, hence no ROC curve, and are not drawn "
              "(plot their false_merge_rate with experiments.plot): " + "; ".join(
                  f"{r.method} {r.n_landmarks} landmarks {r.overlap:.0%} {r.snr_db:g} dB"
                  for r in cells.itertuples()), file=sys.stderr)
    return {kind: t[~t.unrelated.astype(bool)] for kind, t in tables.items()}


def draw_aggregate(directory: Path, wrap: int | None = 4) -> list[Path]:
    """``roc.png``/``.pdf`` of an aggregate directory (``roc.csv``, ``auc.csv``, ``table.csv``), ``wrap``
    panels side by side at most."""
    tables = related_cells({kind: pd.read_csv(directory / f"{kind}.csv") for kind in ("roc", "auc", "table")})
    with plt.rc_context(STYLE):
        return fig3(tables["roc"], tables["auc"], directory, "roc", table=tables["table"], wrap=wrap)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description="Draw figures from aggregated tables.")
    parser.add_argument("results", help="an aggregate directory (roc.csv) or one holding fig1/, fig2/, fig3/")
    args = parser.parse_args(argv)
    directory = Path(args.results)
    try:
        if (directory / "roc.csv").exists():
            made = draw_aggregate(directory)
            print((directory / "table.md").read_text())
        else:
            made = draw_all(directory)
    except FileNotFoundError as exc:
        parser.exit(2, f"error: {exc}\n")
    for path in made:
        print(path)


if __name__ == "__main__":
    main()

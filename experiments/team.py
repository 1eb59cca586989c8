"""Teams of agents: ``merge_many`` against chaining and a spanning tree (results/team/).

    python -m experiments.team                 # about 20 minutes on 2 cores
    python -m experiments.team --teams 5       # a quick look

Synthetic teams (``mm.simulate.make_group``: 100 landmarks per map on
average, neighbours sharing half of their disc, strip layout) are merged
once pairwise by ``consensus``; the same pairwise merges are then
assembled three ways (``placement``): ``joint`` (cycle-consistency test and
joint ML, the method), ``tree`` (maximum spanning tree, no joint
optimisation) and ``chain`` (sequential chaining). Reported per cell and
placement (``table.md``): the share of teams with every agent placed
correctly (rotation within 1°, RMS registration within σ) and its 95 %
Wilson interval, wrong placements, placements whose error lies outside
their own covariance's 99.9 % region (``beyond_cov``, right or wrong:
off by more than the result says, unlike a far map placed within its
honest uncertainty),
agents left unplaced, strangers placed,
track purity and completeness, the fused map's RMSE over the landmarks
seen by two or more maps (``shared_rmse``, in σ) and its ratio to the
chain's and the tree's on the same teams (ratio of sums over teams, 95 %
delta-method interval), and the seconds per team (pairwise merges and
assembly, one core).

Cells: the headline (5 agents, ring, 20 dB, 200 teams, without and with one
stranger), agents 3 / 5 / 10 / 20 x 15 / 20 / 30 dB on the ring and random
topologies, and the chain and star at 20 dB. ``speed.md``: ``merge_many``
end to end on 20-agent teams with ``n_jobs=2``.

Nothing is tuned here: ``merge_many``'s constants (``CYCLE_P``,
``HUBER_K``, ``CANDIDATE_NEIGHBOURS``) were set from their definitions, not
from runs. Teams are drawn from ``SeedSequence([TEAM_SEED, cell key, k])``;
each cell's rows are cached under ``--out``/rows keyed by the cell and a
digest of the library's code, so an interrupted run resumes.
"""

from __future__ import annotations

import argparse
import time
import zlib
from pathlib import Path

import numpy as np
import pandas as pd
from joblib import Parallel, delayed

import mapmerge as mm
from mapmerge import group

from .aggregate import save_table
from .intervals import ratio_interval, wilson
from .trials import code_digest

TEAM_SEED = 900000
N_LANDMARKS, OVERLAP = 100, 0.5
#: (n_agents, snr_db, topology, n_strangers) of every cell: the headline cells (``--headline-teams`` teams)
#: and the grid (``--teams``).
HEADLINE = [(5, 20.0, "ring", 0), (5, 20.0, "ring", 1)]
AGENTS = (3, 5, 10, 20)
GRID = [cell for cell in ([(n, snr, top, 0) for top in ("ring", "random") for snr in (15.0, 20.0, 30.0) for n in AGENTS]
                          + [(n, 20.0, top, 0) for top in ("chain", "star") for n in AGENTS])
        if cell not in HEADLINE]
SPEED_AGENTS, SPEED_TEAMS = 20, 3


def cell_key(n_agents: int, snr_db: float, topology: str, n_strangers: int, n_landmarks: int = N_LANDMARKS,
             overlap: float = OVERLAP, layout: str = "strip") -> int:
    """A stable number for a cell's scientific parameters (its seeds' spawn key; the layout named only
    when it is not the strip, so that strip cells keep their seeds)."""
    text = f"{n_agents}/{snr_db:g}/{topology}/{n_strangers}/{n_landmarks}/{overlap:g}"
    return zlib.crc32((text if layout == "strip" else f"{text}/{layout}").encode())


def team_rows(n_agents: int, snr_db: float, topology: str, n_strangers: int, k: int, n_landmarks: int = N_LANDMARKS,
              overlap: float = OVERLAP, layout: str = "strip", root_seed: int = TEAM_SEED) -> list[dict]:
    """Team k of a cell merged pairwise once and assembled by every placement: a row per placement."""
    key = cell_key(n_agents, snr_db, topology, n_strangers, n_landmarks, overlap, layout)
    team = mm.simulate.make_group(n_agents, n_landmarks, overlap, snr_db, layout=layout, topology=topology,
                                  n_strangers=n_strangers, rng=np.random.SeedSequence([root_seed, key, k]))
    sigmas = np.full(team.n_agents, team.sigma)
    start = time.perf_counter()
    edges = group.pairwise_edges(team.maps, sigmas, [None] * team.n_agents,
                                 group.candidate_pairs(team.maps, sigmas))
    pairwise = time.perf_counter() - start
    rows = []
    for placement in group.PLACEMENTS:
        start = time.perf_counter()
        merged = group.assemble(team.maps, team.covs, edges, 0, placement)
        assembly = time.perf_counter() - start
        err = mm.metrics.group_errors(team, merged)
        counts = merged.edge_counts()
        rows.append({
            "n_agents": n_agents, "snr_db": snr_db, "topology": topology, "n_strangers": n_strangers, "team": k,
            "placement": placement, "all_correct": err["all_correct"], "placed_correct": err["placed_correct"],
            "placed_wrong": err["placed_wrong"], "beyond_cov": err["beyond_cov"], "unplaced": err["unplaced"],
            "strangers_placed": err["strangers_placed"], "track_purity": err["track_purity"],
            "track_completeness": err["track_completeness"], "duplicates": err["duplicates"],
            "fused_rmse": err["fused_rmse"] / team.sigma, "shared_rmse": err["shared_rmse"] / team.sigma,
            "edges_tried": len(edges), "edges_accepted": counts[group.ACCEPTED],
            "edges_inconsistent": counts[group.INCONSISTENT],
            "seconds": pairwise + assembly, "pairwise_seconds": pairwise,
        })
    return rows


def run_cells(cells, n_teams: int, out: Path, n_jobs: int = 2) -> pd.DataFrame:
    """Every cell's ``n_teams`` teams' rows, computed or read from ``out``/rows (one CSV per cell, written whole)."""
    rows_dir = out / "rows"
    rows_dir.mkdir(parents=True, exist_ok=True)
    digest = code_digest()[:12]
    frames = []
    teams = n_teams
    for n_agents, snr, topology, strangers in cells:
        path = rows_dir / f"{n_agents}-{snr:g}-{topology}-{strangers}-{teams}-{digest}.csv"
        if not path.exists():
            start = time.perf_counter()
            rows = Parallel(n_jobs=n_jobs)(delayed(team_rows)(n_agents, snr, topology, strangers, k)
                                           for k in range(teams))
            tmp = path.with_suffix(".tmp")
            pd.DataFrame([r for team in rows for r in team]).to_csv(tmp, index=False)
            tmp.replace(path)
            print(f"{path.name}: {time.perf_counter() - start:.0f} s", flush=True)
        frames.append(pd.read_csv(path))
    return pd.concat(frames, ignore_index=True)


def summary(rows: pd.DataFrame) -> pd.DataFrame:
    """One row per cell and placement (the module docstring's columns)."""
    out = []
    keys = ["n_agents", "snr_db", "topology", "n_strangers"]
    for cell, g in rows.groupby(keys, sort=False):
        ref = {p: g[g.placement == p].set_index("team") for p in group.PLACEMENTS}
        for placement in group.PLACEMENTS:
            r = ref[placement]
            low, high = wilson(np.array([r.all_correct.sum()]), np.array([len(r)]))
            ratios = {}
            for base in ("chain", "tree"):
                both = r.shared_rmse.notna() & ref[base].shared_rmse.notna()
                ratio = r.shared_rmse[both].sum() / ref[base].shared_rmse[both].sum() if both.any() else np.nan
                lo, hi = ratio_interval(r.shared_rmse[both], ref[base].shared_rmse[both])
                ratios[f"rmse_vs_{base}"] = f"{ratio:.3f} [{lo:.3f}, {hi:.3f}]"
            out.append({
                **dict(zip(keys, cell)), "placement": placement, "teams": len(r),
                "all_correct": r.all_correct.mean(), "all_correct_95": f"[{low[0]:.3f}, {high[0]:.3f}]",
                "wrong": int(r.placed_wrong.sum()), "beyond_cov": int(r.beyond_cov.sum()),
                "unplaced": int(r.unplaced.sum()),
                "strangers_placed": int(r.strangers_placed.sum()), "purity": r.track_purity.mean(),
                "completeness": r.track_completeness.mean(), "shared_rmse": r.shared_rmse.mean(), **ratios,
                "edges_inconsistent": int(r.edges_inconsistent.sum()),
                "seconds": r.seconds.median(),
            })
    return pd.DataFrame(out)


#: What the committed cells hold (``headline``'s default note).
NOTE = "100 landmarks per map, neighbours sharing half their disc, `consensus` pairwise merges."


def headline(table: pd.DataFrame, note: str = NOTE) -> str:
    """``summary.md``: one line per cell, the three placements side by side (``note``: what the cells hold)."""
    lines = ["# Teams of agents: merge_many against chaining and a spanning tree", "",
             "Share of teams with every agent placed correctly (joint / tree / chain), wrong placements "
             "(rotation over 1° or RMS registration over σ), placements (right or wrong) outside their own "
             "covariance's 99.9 % region, team agents left unplaced, strangers placed, and the fused map's RMSE over "
             "landmarks seen twice or more (joint, in σ) "
             f"with its ratio to the chain's and the tree's (95 % intervals). {note}", "",
             "| agents | SNR (dB) | topology | strangers | teams | all correct (j / t / c) | wrong (j / t / c) "
             "| beyond own covariance (j / t / c) | unplaced (j) | strangers placed (j) | RMSE joint (σ) "
             "| joint / chain | joint / tree |",
             "|---:|---:|:---|---:|---:|:---|:---|:---|---:|---:|---:|:---|:---|"]
    for _, g in table.groupby(["topology", "n_strangers", "snr_db", "n_agents"], sort=True):
        by = g.set_index("placement")
        j = by.loc["joint"]
        lines.append(
            f"| {j.n_agents} | {j.snr_db:g} | {j.topology} | {j.n_strangers} | {j.teams} "
            f"| {' / '.join(f'{by.loc[p].all_correct:.3f}' for p in group.PLACEMENTS)} "
            f"| {' / '.join(str(by.loc[p].wrong) for p in group.PLACEMENTS)} "
            f"| {' / '.join(str(by.loc[p].beyond_cov) for p in group.PLACEMENTS)} "
            f"| {j.unplaced} | {j.strangers_placed} "
            f"| {j.shared_rmse:.3f} | {j.rmse_vs_chain} | {j.rmse_vs_tree} |")
    return "\n".join(lines) + "\n"


def speed(out: Path) -> pd.DataFrame:
    """``merge_many`` end to end (n_jobs=2) on ``SPEED_TEAMS`` ring teams of ``SPEED_AGENTS`` agents."""
    rows = []
    for k in range(SPEED_TEAMS):
        team = mm.simulate.make_group(SPEED_AGENTS, N_LANDMARKS, OVERLAP, 20.0, topology="ring",
                                      rng=np.random.SeedSequence([TEAM_SEED, 1, k]))
        start = time.perf_counter()
        merged = mm.merge_many(team.maps, team.sigma, n_jobs=2)
        seconds = time.perf_counter() - start
        err = mm.metrics.group_errors(team, merged)
        rows.append({"n_agents": SPEED_AGENTS, "team": k, "pairs_tried": len(merged.edges), "seconds": seconds,
                     "all_correct": err["all_correct"]})
    return pd.DataFrame(rows)


def figure(table: pd.DataFrame, path: Path) -> None:
    """All-correct share and fused RMSE against team size, ring topology, one column per SNR."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import NullFormatter

    grid = table[(table.topology == "ring") & (table.n_strangers == 0)]
    snrs = sorted(grid.snr_db.unique())
    fig, axes = plt.subplots(2, len(snrs), figsize=(3.4 * len(snrs), 5.6), sharex=True, sharey="row",
                             squeeze=False)
    for col, snr in enumerate(snrs):
        cell = grid[grid.snr_db == snr]
        for placement, marker in zip(group.PLACEMENTS, "os^"):
            line = cell[cell.placement == placement].sort_values("n_agents")
            axes[0, col].plot(line.n_agents, line.all_correct, marker=marker, label=placement)
            axes[1, col].plot(line.n_agents, line.shared_rmse, marker=marker, label=placement)
        axes[0, col].set_title(f"ring, {snr:g} dB")
        axes[1, col].set_xlabel("agents in the team")
        axes[1, col].set_xscale("log")
        axes[1, col].set_xticks(list(AGENTS), [str(n) for n in AGENTS])
        axes[1, col].xaxis.set_minor_formatter(NullFormatter())
    axes[0, 0].set_ylabel("teams with every agent\nplaced correctly")
    axes[1, 0].set_ylabel("fused-map RMSE, shared\nlandmarks (σ)")
    axes[0, -1].legend(title="placement", loc="center left", bbox_to_anchor=(1.02, 0.5))
    fig.tight_layout()
    fig.savefig(path, dpi=150, metadata={"Software": None})
    plt.close(fig)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description="merge_many against chaining and a spanning tree on teams.")
    parser.add_argument("--out", default="results/team")
    parser.add_argument("--teams", type=int, default=20, help="teams per grid cell")
    parser.add_argument("--headline-teams", type=int, default=200, help="teams per headline cell")
    parser.add_argument("--n-jobs", type=int, default=2)
    args = parser.parse_args(argv)
    if min(args.teams, args.headline_teams) < 1 or args.n_jobs == 0 or args.n_jobs < -1:
        parser.error("--teams and --headline-teams must be >= 1 and --n-jobs a positive integer or -1")
    out = Path(args.out)
    rows = pd.concat([run_cells(HEADLINE, args.headline_teams, out, args.n_jobs),
                      run_cells(GRID, args.teams, out, args.n_jobs)], ignore_index=True)
    table = summary(rows)
    for path in save_table(table, out / "table") + save_table(speed(out), out / "speed"):
        print(path)
    (out / "summary.md").write_text(headline(table))
    figure(table, out / "team.png")
    print((out / "table.md").read_text())


if __name__ == "__main__":
    main()

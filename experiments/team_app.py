"""Teams of agents as a Hydra app: one team cell per job (conf/team.yaml, presets in conf/team_preset/).

    python -m experiments.team_app team.n_agents=10 team.snr_db=15          # one cell
    python -m experiments.team_app -m team.n_agents=3,5,10 team.topology=ring,star
    python -m experiments.team_app team_preset=grid                          # agents x SNR x topology
    python -m experiments.team_app team_preset=smoke                         # a quick look

Each job draws ``n_teams`` teams of its cell (``mm.simulate.make_group``
with the ``team.*`` settings, team k from ``SeedSequence([seed, cell key,
k])`` as ``experiments.team`` draws them), merges each pairwise once and
assembles the same pairwise merges by ``merge_many``'s three placements.
It writes into its Hydra output directory ``rows.csv`` (one row per team
and placement; with the code digest in ``rows.digest``, its resume point)
and ``summary.csv`` / ``summary.md``; at the end of a multirun,
``<sweep dir>/summary.md`` and ``table.csv`` hold every cell of every run
under the sweep's name. A bad value is one line naming the key, exit
status 2, before any team is drawn.
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path

import hydra
import pandas as pd
from hydra.core.hydra_config import HydraConfig
from hydra.experimental.callback import Callback
from joblib import Parallel, delayed
from omegaconf import DictConfig

import mapmerge as mm
from mapmerge.simulate import ScenarioError

from .aggregate import save_table
from .schema import CONF_DIR
from .team import headline, summary, team_rows
from .trials import code_digest

log = logging.getLogger(__name__)

#: The ``team.*`` keys, in ``make_group``'s order.
TEAM_KEYS = ("n_agents", "n_landmarks", "overlap", "snr_db", "topology", "layout", "n_strangers")


def validate(cfg: DictConfig) -> dict:
    """The cell's ``make_group`` arguments, or a one-line ValueError naming the bad key."""
    for key, low in (("n_teams", 1), ("seed", 0)):
        value = cfg.get(key)
        if not (isinstance(value, int) and not isinstance(value, bool) and value >= low):
            raise ValueError(f"{key}={value!r}: must be an integer >= {low}")
    n_jobs = cfg.get("n_jobs")
    if not (isinstance(n_jobs, int) and not isinstance(n_jobs, bool) and (n_jobs >= 1 or n_jobs == -1)):
        raise ValueError(f"n_jobs={n_jobs!r}: must be a positive integer or -1")
    unknown = set(cfg.team) - set(TEAM_KEYS)
    if unknown:
        raise ValueError(f"team.{min(unknown)}: unknown key; the team keys are {list(TEAM_KEYS)}")
    cell = {key: cfg.team[key] for key in TEAM_KEYS}
    try:
        # make_group checks every argument before it draws anything but the geometry of a random topology.
        mm.simulate.make_group(**{k: cell[k] for k in ("n_agents", "n_landmarks", "overlap", "snr_db")},
                               topology=cell["topology"], layout=cell["layout"], n_strangers=cell["n_strangers"],
                               rng=0)
    except ScenarioError as exc:
        raise ValueError(f"team.{exc.argument}={exc.value!r}: {exc.rule}") from None
    return cell


def run(cfg: DictConfig, output_dir: str | Path) -> pd.DataFrame:
    """One cell's teams into ``output_dir`` (``rows.csv``, ``summary.csv``/``.md``); returns the summary."""
    cell = validate(cfg)
    out = Path(output_dir)
    out.mkdir(parents=True, exist_ok=True)
    rows_path, digest_path = out / "rows.csv", out / "rows.digest"
    digest = f"{code_digest()} {cfg.seed} {cfg.n_teams}"
    if rows_path.exists() and digest_path.exists() and digest_path.read_text() == digest:
        log.info("%s: the cell's %d teams are already there", rows_path, cfg.n_teams)
        rows = pd.read_csv(rows_path)
    else:
        log.info("%d teams to run: %s", cfg.n_teams, cell)
        teams = Parallel(n_jobs=cfg.n_jobs)(
            delayed(team_rows)(cell["n_agents"], float(cell["snr_db"]), cell["topology"], cell["n_strangers"], k,
                               cell["n_landmarks"], float(cell["overlap"]), cell["layout"], cfg.seed)
            for k in range(cfg.n_teams))
        rows = pd.DataFrame([r for team in teams for r in team])
        for key in ("n_landmarks", "overlap", "layout"):
            rows[key] = cell[key]
        tmp = rows_path.with_suffix(".tmp")
        rows.to_csv(tmp, index=False)
        tmp.replace(rows_path)
        digest_path.write_text(digest)
    table = summary(rows)
    save_table(table, out / "summary")
    (out / "summary.md").write_text(headline(table, _note(cell)))
    return table


def _note(cell: dict) -> str:
    return (f"{cell['n_landmarks']} landmarks per map, neighbours sharing {cell['overlap']:g} of their disc, "
            f"{cell['layout']} layout, `consensus` pairwise merges.")


def aggregate(sweep_dir: str | Path) -> Path | None:
    """Every cell under ``sweep_dir`` (each job's ``rows.csv``) into its ``summary.md`` and ``table.csv``."""
    sweep_dir = Path(sweep_dir)
    frames = [pd.read_csv(p) for p in sorted(sweep_dir.rglob("rows.csv"))]
    if not frames:
        return None
    rows = pd.concat(frames, ignore_index=True)
    table = summary(rows)
    save_table(table, sweep_dir / "table")
    first = rows.iloc[0]
    path = sweep_dir / "summary.md"
    path.write_text(headline(table, _note({k: first[k] for k in ("n_landmarks", "overlap", "layout")})))
    return path


class AggregateTeams(Callback):
    """At the end of a multirun: ``aggregate`` the sweep directory (every run under the sweep's name)."""

    def on_multirun_end(self, config, **kwargs) -> None:
        path = aggregate(config.hydra.sweep.dir)
        if path is not None:
            log.info("every cell of the sweep: %s", path)


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="team")
def main(cfg: DictConfig) -> None:
    try:
        table = run(cfg, HydraConfig.get().runtime.output_dir)
    except ValueError as exc:
        print(f"experiments.team_app: error: {exc}", file=sys.stderr)
        sys.exit(2)
    log.info("\n%s", table[["placement", "teams", "all_correct", "wrong", "unplaced", "shared_rmse"]]
             .to_string(index=False))


if __name__ == "__main__":
    main()

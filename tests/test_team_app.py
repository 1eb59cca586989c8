"""The teams Hydra app (experiments.team_app): configs composed with Hydra's compose API."""

import pandas as pd
import pytest
from hydra import compose, initialize_config_dir

from experiments import team_app
from experiments.schema import CONF_DIR


def _cfg(*overrides, hydra=False):
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose(config_name="team", overrides=list(overrides), return_hydra_config=hydra)


def test_a_cell_runs_resumes_and_aggregates(tmp_path):
    cfg = _cfg("n_teams=2", "n_jobs=1", "team.n_agents=3", "team.n_landmarks=40", "team.snr_db=30")
    table = team_app.run(cfg, tmp_path / "cell")
    assert table.placement.tolist() == ["joint", "tree", "chain"] and (table.teams == 2).all()
    rows = pd.read_csv(tmp_path / "cell" / "rows.csv")
    assert len(rows) == 6 and set(rows.n_landmarks) == {40}
    stamp = (tmp_path / "cell" / "rows.csv").stat().st_mtime_ns
    team_app.run(cfg, tmp_path / "cell")  # the same cell again: read, not recomputed
    assert (tmp_path / "cell" / "rows.csv").stat().st_mtime_ns == stamp
    assert "| 3 | 30 | ring |" in team_app.aggregate(tmp_path).read_text()


def test_the_presets_compose():
    grid = _cfg("team_preset=grid", hydra=True)
    assert grid.name == "grid" and grid.hydra.sweeper.params["team.topology"] == "ring,random"
    assert _cfg("team_preset=smoke").team.n_landmarks == 40


@pytest.mark.parametrize("override, message", [
    ("team.n_agents=1", "team.n_agents=1: must be an integer"),
    ("team.topology=mesh", "team.topology='mesh': must be one of"),
    ("team.overlap=1.5", "team.overlap=1.5"),
    ("n_teams=0", "n_teams=0: must be an integer >= 1"),
    ("n_jobs=0", "n_jobs=0"),
    ("+team.colour=red", "team.colour: unknown key"),
])
def test_bad_values_are_one_line_errors_and_write_nothing(tmp_path, override, message):
    with pytest.raises(ValueError, match=message):
        team_app.run(_cfg(override), tmp_path / "cell")
    assert not (tmp_path / "cell").exists()

"""The Hydra harness: config composition, reproducibility, resume, scale-out, CLI."""

import hashlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest
from hydra import compose, initialize_config_dir

from experiments.run import CONF_DIR, run
from experiments.schema import ConfigError, validate

PRESETS = sorted(p.stem for p in (Path(CONF_DIR) / "experiment").glob("*.yaml"))
GROUPS = {g: sorted(p.stem for p in (Path(CONF_DIR) / g).glob("*.yaml")) for g in ("scenario", "matcher", "mc")}


def _compose(overrides=(), hydra=False):
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose("config", overrides=list(overrides), return_hydra_config=hydra)


def _digest(path):
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def _small(**mc):
    overrides = ["scenario=small", "scenario.snr_db=25", "mc.n_trials=30", "mc.chunk_size=7",
                 "mc.progress=false"] + [f"mc.{k}={v}" for k, v in mc.items()]
    return _compose(overrides)


@pytest.mark.parametrize("group, option", [(g, o) for g, opts in GROUPS.items() for o in opts])
def test_every_group_option_composes(group, option):
    # A real data set is one fixed map pair: one trial.
    extra = ["mc.n_trials=1"] if option == "victoria_park" else []
    cfg = _compose([f"{group}={option}", *extra])
    validate(cfg)


@pytest.mark.parametrize("preset", PRESETS)
def test_every_preset_composes(preset):
    cfg = _compose([f"experiment={preset}"], hydra=True)
    validate(cfg)
    assert cfg.name == preset
    assert cfg.hydra.job.chdir is False
    assert cfg.hydra.sweeper.params


def test_fig3_preset_is_the_papers_grid():
    from hydra.core.override_parser.overrides_parser import OverridesParser

    from experiments.run import expand_sweep

    cfg = _compose(["experiment=fig3"], hydra=True)
    sweep = OverridesParser.create().parse_overrides([f"{k}={v}" for k, v in cfg.hydra.sweeper.params.items()])
    cells = {tuple(float(o.split("=")[1]) for o in job) for job in expand_sweep(sweep)}
    assert cells == {(n, ov, snr) for n in (10, 20) for ov in (0.75, 0.5) for snr in range(0, 45, 5)}
    # 10,000 trials per curve as in the paper, on both cores: cells as parallel jobs.
    assert cfg.mc.n_trials == 10000
    assert cfg.hydra.launcher.n_jobs == 2 and cfg.mc.n_jobs == 1


@pytest.mark.parametrize(
    "override, key",
    [
        ("scenario.overlap=1.5", "scenario.overlap"),
        ("scenario.overlap=0", "scenario.overlap"),
        ("scenario.n_landmarks=2", "scenario.n_landmarks"),
        ("mc.n_jobs=0", "mc.n_jobs"),
        ("mc.chunk_size=0", "mc.chunk_size"),
        ("matcher.objective=max", "matcher.objective"),
        ("matcher.taus=[chi2:2]", "matcher.taus"),
        ("mc.backend=spark", "mc.backend"),
    ],
)
def test_validate_names_the_key(override, key):
    with pytest.raises(ConfigError, match=key):
        validate(_compose([override]))


def _cli(args, cwd, timeout=120):
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    return subprocess.run([sys.executable, "-m", "experiments.run", *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=timeout)


@pytest.mark.parametrize(
    "args, key",
    [
        (["scenario.overlap=1.5"], "scenario.overlap"),
        (["-m", "scenario.n_landmarks=2,10"], "scenario.n_landmarks"),
        (["-m", "experiment=smoke", "mc.n_jobs=0"], "mc.n_jobs"),
        (["scenario.foo=1"], "foo"),
        (["mc.n_trials=abc"], "n_trials"),
        (["-m", "experiment=smoke", "hydra/launcher=joblib"], "mc.n_jobs"),
    ],
)
def test_invalid_overrides_fail_fast_and_write_nothing(tmp_path, args, key):
    proc = _cli(args, tmp_path)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:") and key in lines[0], proc.stderr
    assert list(tmp_path.iterdir()) == []


def test_n_jobs_and_chunk_size_do_not_change_results(tmp_path):
    a = run(_small(n_jobs=1, chunk_size=7), tmp_path / "a").parent
    b = run(_small(n_jobs=2, chunk_size=4), tmp_path / "b").parent
    for name in ("trials.parquet", "pairs.parquet"):
        assert _digest(a / name) == _digest(b / name), name
    trials = pd.read_parquet(a / "trials.parquet")
    assert sorted(trials.trial.unique()) == list(range(30))
    assert set(trials.tau) == {"oracle", "chi2:0.01", "chi2:0.001"}
    assert (trials[trials.tau == "oracle"].fp == 0).all()


def test_resume_after_deleting_chunks_is_identical(tmp_path):
    out = run(_small(), tmp_path).parent
    before = {n: _digest(out / n) for n in ("trials.parquet", "pairs.parquet")}
    chunks = sorted((out / "chunks").glob("*.trials.parquet"))
    for path in chunks[1:3]:
        path.unlink()
    mtime = chunks[0].stat().st_mtime_ns
    run(_small(), tmp_path)
    assert chunks[0].stat().st_mtime_ns == mtime  # finished chunk not recomputed
    assert {n: _digest(out / n) for n in before} == before


def test_chunks_of_other_code_are_not_reused(tmp_path, monkeypatch):
    out = run(_small(), tmp_path).parent
    before = set((out / "chunks").glob("*.trials.parquet"))
    monkeypatch.setattr("experiments.run.code_digest", lambda: "another version of the library")
    run(_small(), tmp_path)
    after = set((out / "chunks").glob("*.trials.parquet"))
    assert len(after - before) == len(before)  # every chunk recomputed under a new key


def test_kill_9_then_rerun_matches_uninterrupted(tmp_path):
    args = ["scenario.n_landmarks=100", "mc.n_trials=300", "mc.chunk_size=10", "mc.n_jobs=1",
            "mc.progress=false", "name=kill"]
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    proc = subprocess.Popen([sys.executable, "-m", "experiments.run", *args], cwd=tmp_path, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 60
    while time.time() < deadline:
        done = list(tmp_path.rglob("chunks/*.trials.parquet"))
        if len(done) >= 3:
            break
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    chunk_dir = done[0].parent
    assert not (chunk_dir.parent / "trials.parquet").exists(), "run finished before the kill"
    assert _cli(args, tmp_path).returncode == 0
    ref = _cli(args + ["name=ref"], tmp_path)
    assert ref.returncode == 0
    ref_dir = next((tmp_path / "outputs" / "runs" / "ref").iterdir())
    for name in ("trials.parquet", "pairs.parquet"):
        assert _digest(chunk_dir.parent / name) == _digest(ref_dir / name)


def test_hydra_joblib_launcher_runs_jobs_in_parallel(tmp_path):
    proc = _cli(["-m", "experiment=smoke", "hydra/launcher=joblib", "hydra.launcher.n_jobs=2",
                 "mc.n_jobs=1", "mc.progress=false"], tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    sweep = tmp_path / "outputs" / "sweeps" / "smoke"
    assert len(list(sweep.glob("*/trials.parquet"))) == 2
    assert (sweep / "aggregate" / "table.csv").exists()


def test_dask_backend_gives_identical_results(tmp_path):
    distributed = pytest.importorskip("dask.distributed")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster:
        d = run(_small(backend="dask", address=cluster.scheduler_address), tmp_path / "dask").parent
    ref = run(_small(), tmp_path / "loky").parent
    for name in ("trials.parquet", "pairs.parquet"):
        assert _digest(d / name) == _digest(ref / name)


def test_multirun_end_to_end_through_aggregation_and_figures(tmp_path):
    results = tmp_path / "results"
    fig3 = _cli(["-m", "experiment=fig3", "mc.n_trials=12", "mc.chunk_size=6",
                 "scenario.snr_db=15,40", f"aggregate_dir={results / 'fig3'}",
                 "mc.progress=false"], tmp_path, timeout=300)
    assert fig3.returncode == 0, fig3.stderr[-2000:]
    smoke = _cli(["-m", "experiment=smoke", f"aggregate_dir={results / 'fig1'}"], tmp_path)
    assert smoke.returncode == 0, smoke.stderr[-2000:]
    (results / "fig2").mkdir()
    os.link(results / "fig1" / "examples_landmarks.csv", results / "fig2" / "examples_landmarks.csv")

    auc = pd.read_csv(results / "fig3" / "auc.csv")
    assert len(auc) == 8 and auc.n_trials.eq(12).all()
    assert (auc[auc.snr_db == 40].auc.to_numpy() > auc[auc.snr_db == 15].auc.to_numpy()).all()
    table = pd.read_csv(results / "fig3" / "table.csv")
    assert set(table.tau) == {"oracle", "chi2:0.01", "chi2:0.001"} and len(table) == 24
    roc = pd.read_csv(results / "fig3" / "roc.csv")
    assert roc.groupby(["n_landmarks", "overlap", "snr_db"]).p_fa.is_monotonic_increasing.all()
    assert (results / "fig1" / "table.md").read_text().startswith("|")
    examples = pd.read_csv(results / "fig1" / "examples_landmarks.csv")
    assert set(examples["kind"]) == {"p", "q", "merged", "truth"}

    from experiments.figures import draw_all

    made = draw_all(results)
    assert {p.name for p in made} == {f"fig{i}.{e}" for i in (1, 2, 3) for e in ("png", "pdf")}
    assert all(p.stat().st_size > 10_000 for p in made)


def test_victoria_park_preset_runs_real_data(tmp_path):
    proc = _cli(["-m", "experiment=victoria_park", "scenario.cut=3483", "scenario.source=reference",
                 "matcher.method=paper,consensus", "matcher.use_cov=false", "mc.progress=false"], tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    runs = sorted((tmp_path / "outputs" / "sweeps" / "victoria_park").glob("*/trials.parquet"))
    trials = pd.concat([pd.read_parquet(r) for r in runs]).set_index("method")
    assert list(trials.n_p) == [82, 82] and list(trials.n_common_landmarks) == [66, 66]
    assert trials.loc["consensus", "rot_err_deg"] < 1 and trials.loc["consensus", "trans_err"] < 1
    assert (tmp_path / "outputs" / "sweeps" / "victoria_park" / "aggregate" / "table.csv").exists()


def test_example_triangle_status_prefers_the_telling_pair():
    import numpy as np

    from experiments.examples import _triangle_status

    pairs = np.array([[0, 5], [0, 6], [1, 7], [2, 8]])
    is_true = np.array([True, False, False, True])
    declared = np.array([True, False, False, False])
    common = np.array([[0, 5], [1, 9], [2, 8]])
    status = _triangle_status(4, 0, pairs, is_true, declared, common)
    assert list(status) == ["tp", "unpaired", "md", "other"]


def test_readme_includes_are_refreshed_from_results(tmp_path):
    from experiments.docs import refresh

    (tmp_path / "results").mkdir()
    (tmp_path / "results" / "t.md").write_text("# Title\n\n## Part\n\n| a |\n|---|\n| 1 |\n![f](f.png)\n")
    readme = tmp_path / "README.md"
    readme.write_text("intro\n<!-- include: results/t.md -->\nold numbers\n<!-- end include -->\nrest\n")
    assert refresh(readme) == ["results/t.md"]
    text = readme.read_text()
    assert "old numbers" not in text and "# Title" not in text
    assert "#### Part" in text and "| 1 |" in text and "![f](results/f.png)" in text
    assert text.startswith("intro\n") and text.endswith("<!-- end include -->\nrest\n")

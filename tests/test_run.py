"""Running cells: bit-identical results for any workers, chunks, backend or resume; interruption; output."""

import os
import signal
import subprocess
import sys
import time

import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from experiments.run import run
from harness_utils import ROOT, cli, digest, small


def test_n_jobs_and_chunk_size_do_not_change_results(tmp_path):
    a = run(small(n_jobs=1, chunk_size=7), tmp_path / "a").parent
    b = run(small(n_jobs=2, chunk_size=4), tmp_path / "b").parent
    for name in ("trials.parquet", "pairs.parquet"):
        assert digest(a / name) == digest(b / name), name
    trials = pd.read_parquet(a / "trials.parquet")
    assert sorted(trials.trial.unique()) == list(range(30))
    assert set(trials.tau) == {"oracle", "chi2:0.01", "chi2:0.001"}


def test_resume_after_deleting_chunks_is_identical(tmp_path):
    out = run(small(), tmp_path).parent
    before = {n: digest(out / n) for n in ("trials.parquet", "pairs.parquet")}
    chunks = sorted((out / "chunks").rglob("*.trials.parquet"))
    for path in chunks[1:3]:
        path.unlink()
    mtime = chunks[0].stat().st_mtime_ns
    run(small(), tmp_path)
    assert chunks[0].stat().st_mtime_ns == mtime  # finished chunk not recomputed
    assert {n: digest(out / n) for n in before} == before


def test_more_trials_compute_only_the_new_ones_and_equal_a_fresh_run(tmp_path, caplog):
    cache = tmp_path / "cache"
    run(small(n_trials=6, n_jobs=1), tmp_path / "first", cache)
    with caplog.at_level("INFO", logger="experiments.run"):
        more = run(small(n_trials=15, n_jobs=1), tmp_path / "more", cache).parent
    assert "15 trials, 6 cached, 9 to run in " in caplog.text
    fresh = run(small(n_trials=15, n_jobs=1), tmp_path / "fresh", tmp_path / "other_cache").parent
    for name in ("trials.parquet", "pairs.parquet"):
        assert digest(more / name) == digest(fresh / name), name
    # Fewer trials than cached: read from the cache, nothing run, the same rows as a fresh run of as many.
    caplog.clear()
    with caplog.at_level("INFO", logger="experiments.run"):
        fewer = run(small(n_trials=10, n_jobs=1), tmp_path / "fewer", cache).parent
    assert "10 trials, 10 cached, 0 to run in 0 chunks" in caplog.text
    pd.testing.assert_frame_equal(pd.read_parquet(fewer / "pairs.parquet"),
                                  pd.read_parquet(fresh / "pairs.parquet").query("trial < 10").reset_index(drop=True))


def test_progress_bars_are_quiet_in_ci_and_with_hydra_verbose_false(monkeypatch):
    from experiments import progress

    monkeypatch.delenv("CI", raising=False)
    progress.set_quiet(["hydra.run.dir=x"])
    assert progress.enabled(True) and not progress.enabled(False)
    progress.set_quiet(["hydra.verbose=false"])
    assert not progress.enabled(True)
    progress.set_quiet([])
    monkeypatch.setenv("CI", "true")
    assert not progress.enabled(True)


def test_cover_reads_cached_chunks_and_lists_the_gaps():
    from experiments.run import cover

    # Overlapping chunks (two processes extended one cell) and one past n: no trial read twice.
    pieces, missing = cover([(0, 10), (5, 20), (30, 40), (45, 60)], 50)
    assert pieces == [(0, 10, 0, 10), (5, 20, 10, 20), (30, 40, 30, 40), (45, 60, 45, 50)]
    assert missing == [(20, 30), (40, 45)]
    assert cover([], 7) == ([], [(0, 7)])


def test_run_summaries_follow_the_run_and_aggregate_as_its_trials(tmp_path):
    from experiments.aggregate import SUMMARIES, aggregate, summary_path

    out = run(small(n_trials=12), tmp_path).parent
    assert pd.read_parquet(summary_path(out, "auc")).n_trials.item() == 12
    # More trials in the same directory: the run's summaries are rewritten with its files.
    run(small(n_trials=20), tmp_path)
    assert pd.read_parquet(summary_path(out, "auc")).n_trials.item() == 20
    aggregate([out], tmp_path / "from_summaries")
    # A summary written by other code (its digest differs) is not read, whatever it says.
    auc = pq.read_table(summary_path(out, "auc"))
    auc = auc.set_column(auc.schema.get_field_index("n_trials"), "n_trials", pa.array([999]))
    pq.write_table(auc.replace_schema_metadata({**auc.schema.metadata, b"mapmerge.summary_digest": b"other"}),
                   summary_path(out, "auc"))
    aggregate([out], tmp_path / "other_code")
    for kind in SUMMARIES:
        summary_path(out, kind).unlink()
    aggregate([out], tmp_path / "from_trials")
    for name in ("roc.csv", "auc.csv", "table.csv", "timing.csv", "table.md"):
        assert (tmp_path / "from_summaries" / name).read_bytes() == (tmp_path / "from_trials" / name).read_bytes()
        assert (tmp_path / "other_code" / name).read_bytes() == (tmp_path / "from_trials" / name).read_bytes()


@pytest.mark.parametrize("digest_name, other", [("code_digest", "another version of the library"),
                                                 ("arithmetic_digest", "AVX-512 kernels"),
                                                 ("library_versions", {"numpy": "2.0.0", "scipy": "1.13.0"})])
def test_chunks_of_other_code_libraries_or_arithmetic_are_not_reused(tmp_path, monkeypatch, digest_name, other):
    # One process: the patched digest must also be the workers' (see the next test).
    out = run(small(n_jobs=1), tmp_path).parent
    before = set((out / "chunks").rglob("*.trials.parquet"))
    monkeypatch.setattr(f"experiments.trials.{digest_name}", lambda: other)
    run(small(n_jobs=1), tmp_path)
    after = set((out / "chunks").rglob("*.trials.parquet"))
    assert len(after - before) == len(before)  # every chunk recomputed under a new key


def test_a_worker_whose_arithmetic_differs_from_the_drivers_refuses_its_chunk():
    from omegaconf import OmegaConf

    from experiments.run import _chunk_job
    from experiments.trials import arithmetic_digest

    cfg = small()
    args = (0, OmegaConf.to_container(cfg.scenario), OmegaConf.to_container(cfg.matcher), 0, 2, None, os.getpid())
    assert _chunk_job(*args, arithmetic_digest())[2] is not None
    with pytest.raises(RuntimeError, match=r"computes numpy's sin/cos/exp/log/arctan2 with other bits"):
        _chunk_job(*args, "a driver with AVX-512 kernels")


#: A cell slow enough (consensus, ~20 ms a trial, 12 chunks) that stopping it after 3 chunks has seconds of margin.
SLOW_CELL = ["scenario.snr_db=30", "matcher.method=consensus", "matcher.taus=[chi2:0.01]", "mc.n_trials=60",
             "mc.chunk_size=5", "mc.n_jobs=1", "mc.progress=false"]


def _start(args, cwd):
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    # As in a terminal: a shell starts background jobs (a CI script's `make test &`, nohup) with SIGINT
    # ignored, the child would inherit that and Ctrl-C could not be simulated.
    return subprocess.Popen([sys.executable, "-m", "experiments.run", *args], cwd=cwd, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


def _wait_for_chunks(cwd, count):
    deadline = time.time() + 120
    while time.time() < deadline:
        done = list(cwd.glob("outputs/cache/trials/*/*.trials.parquet"))
        if len(done) >= count:
            return done[0].parent
        time.sleep(0.05)
    raise AssertionError("no chunks written")


# SIGKILL (nothing cleaned up) in the default suite; Ctrl-C (SIGINT) with the long runs (make test-all).
@pytest.mark.parametrize("how", [signal.SIGKILL, pytest.param(signal.SIGINT, marks=pytest.mark.slow)])
def test_interrupted_run_resumes_to_the_uninterrupted_result(tmp_path, how):
    proc = _start([*SLOW_CELL, "name=cut"], tmp_path)
    _wait_for_chunks(tmp_path, 3)
    os.killpg(proc.pid, how)  # the whole process group, as Ctrl-C in a terminal
    _, err = proc.communicate()
    (run_dir,) = (tmp_path / "outputs" / "runs" / "cut").iterdir()
    assert not (run_dir / "trials.parquet").exists()
    if how == signal.SIGINT:
        assert proc.returncode == 130
        lines = [line for line in err.splitlines() if "][INFO]" not in line]
        assert len(lines) == 1 and lines[0].startswith("interrupted: ") and "rerun the same command" in lines[0]
    assert cli([*SLOW_CELL, "name=cut"], tmp_path).returncode == 0
    # The reference computes every trial afresh: a trial cache of its own.
    assert cli([*SLOW_CELL, "name=ref", f"output_root={tmp_path / 'ref'}"], tmp_path).returncode == 0
    ref_dir = next((tmp_path / "ref" / "runs" / "ref").iterdir())
    for name in ("trials.parquet", "pairs.parquet"):
        assert digest(run_dir / name) == digest(ref_dir / name)


def test_a_single_run_prints_its_numbers_and_names_dirs_plainly(tmp_path):
    proc = cli(["scenario=small", "mc.n_trials=20", "mc.progress=false", "matcher.taus=[oracle,chi2:0.01]"], tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "| τ rule" in proc.stdout and "chi2:0.01" in proc.stdout and "P_FA" in proc.stdout
    (run_dir,) = (tmp_path / "outputs" / "runs" / "default").iterdir()
    assert "\\" not in run_dir.name and "chi2-0.01" in run_dir.name
    assert "RuntimeWarning" not in proc.stderr
    # Its rows in the results store: one per τ rule, its directory recorded.
    from experiments.results import load

    rows = load(tmp_path / "outputs")
    assert sorted(rows.tau) == ["chi2:0.01", "oracle"] and set(rows.run_dir) == {str(run_dir)}
    assert (rows["mc.n_trials"] == 20).all() and (rows.n_trials == 20).all()


def test_results_store_holds_every_run_and_answers_queries(tmp_path, capsys):
    from experiments.results import load, main, store_file

    store = tmp_path / "store"
    for snr in (15, 25):
        cfg = small(n_trials=6, n_jobs=1)
        cfg.scenario.snr_db, cfg.matcher.taus = snr, ["chi2:0.01"]
        run(cfg, tmp_path / f"run{snr}", tmp_path / "cache", store)
    run(cfg, tmp_path / "run25", tmp_path / "cache", store)  # a rerun of a directory replaces its rows
    assert len(list(store.iterdir())) == 2 and store_file(store, tmp_path / "run25").exists()
    rows = pd.read_parquet(store)  # the dataset read whole, as any pandas user would
    assert sorted(rows["scenario.snr_db"]) == [15.0, 25.0] and rows["matcher.taus"].eq('["chi2:0.01"]').all()
    assert ((rows.found_rate_low <= rows.found_rate) & (rows.found_rate <= rows.found_rate_high)).all()
    assert ((rows.p_d_low <= rows.p_d + 1e-12) & (rows.p_d <= rows.p_d_high + 1e-12)).all()
    main([str(store), "--where", "scenario.snr_db == 15", "--columns", "matcher.method,found_rate"])
    out = capsys.readouterr().out
    assert out.count("| paper") == 1 and "found_rate" in out
    main([str(store), "--where", "scenario.snr_db > 20", "--out", str(tmp_path / "sel.csv")])
    assert pd.read_csv(tmp_path / "sel.csv")["scenario.snr_db"].tolist() == [25.0]
    assert load(tmp_path / "run15")["scenario.snr_db"].tolist() == [15.0]  # a run directory's own rows
    with pytest.raises(SystemExit) as exit_:
        main([str(store), "--where", "snr_db ==="])
    assert exit_.value.code == 2 and capsys.readouterr().err.startswith("error: --where 'snr_db ===' is invalid")


def test_hydra_joblib_launcher_gives_each_cell_its_own_results_and_aggregates_them(tmp_path):
    proc = cli(["-m", "experiment=smoke", "hydra/launcher=joblib", "hydra.launcher.n_jobs=2",
                "mc.n_jobs=1", "mc.progress=false"], tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    sweep = tmp_path / "outputs" / "sweeps" / "smoke"
    from experiments.aggregate import aggregate
    from harness_utils import compose_config

    # A cell's trials are those of the same cell run alone, in this process.
    (job,) = sweep.glob("*snr_db=40*/trials.parquet")
    alone = run(compose_config(["experiment=smoke", "scenario.snr_db=40", "mc.n_jobs=1", "mc.progress=false",
                                "mc.examples=0"]), tmp_path / "alone")
    assert digest(job) == digest(alone)
    # The multirun's aggregate is the aggregation of exactly its two runs.
    aggregate(sorted(p.parent for p in sweep.glob("*/trials.parquet")), tmp_path / "again")
    table = pd.read_csv(sweep / "aggregate" / "table.csv")
    assert sorted(set(table.snr_db)) == [20, 40] and set(table.n_trials) == {40}
    assert (sweep / "aggregate" / "table.csv").read_bytes() == (tmp_path / "again" / "table.csv").read_bytes()


def test_dask_backend_gives_identical_results(tmp_path):
    distributed = pytest.importorskip("dask.distributed")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster:
        d = run(small(backend="dask", address=cluster.scheduler_address), tmp_path / "dask").parent
    ref = run(small(), tmp_path / "loky").parent
    for name in ("trials.parquet", "pairs.parquet"):
        assert digest(d / name) == digest(ref / name)


def test_victoria_park_preset_runs_real_data(tmp_path):
    proc = cli(["-m", "experiment=victoria_park", "scenario.cut=3483", "scenario.source=reference",
                "matcher.method=paper,consensus", "matcher.use_cov=false", "mc.progress=false"], tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    runs = sorted((tmp_path / "outputs" / "sweeps" / "victoria_park").glob("*/trials.parquet"))
    trials = pd.concat([pd.read_parquet(r) for r in runs]).set_index("method")
    assert list(trials.n_p) == [82, 82] and list(trials.n_common_landmarks) == [66, 66]
    assert trials.loc["consensus", "rot_err_deg"] < 1 and trials.loc["consensus", "trans_err"] < 1
    table = pd.read_csv(tmp_path / "outputs" / "sweeps" / "victoria_park" / "aggregate" / "table.csv")
    assert sorted(table.method) == ["consensus", "paper"] and (table.kind == "victoria_park").all()
    assert table.set_index("method").loc["consensus", "success_rate"] == 1.0
    # The driver's table: consensus is right for the trees it paired, and its fused map is scored.
    from experiments.victoria import load_runs, table

    t = table(*load_runs(tmp_path / "outputs" / "sweeps" / "victoria_park")).set_index("method")
    assert t.loc["consensus", "rot err vs its correct pairs' fit (deg)"] < 0.5
    assert 0 < t.loc["consensus", "fused RMSE (m)"] < 1
    # Both oracles pair most of the 66 common trees of the reference maps.
    assert t.loc["consensus", "oracle correct"] >= 56 and t.loc["consensus", "transform oracle correct"] >= 56

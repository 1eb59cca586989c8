"""Config composition and validation: every preset composes, bad values fail fast with one line."""

import os
import subprocess
import sys
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from experiments.preflight import sweep_jobs
from experiments.schema import CONF_DIR, ConfigError, validate
from harness_utils import ROOT, cli, compose_config

PRESETS = sorted(p.stem for p in (Path(CONF_DIR) / "experiment").glob("*.yaml"))
GROUPS = {g: sorted(p.stem for p in (Path(CONF_DIR) / g).glob("*.yaml")) for g in ("scenario", "matcher", "mc")}


@pytest.mark.parametrize("group, option", [(g, o) for g, opts in GROUPS.items() for o in opts])
def test_every_group_option_composes_to_its_file(group, option):
    # A real data set is one fixed map pair: one trial.
    extra = ["mc.n_trials=1"] if option == "victoria_park" else []
    cfg = compose_config([f"{group}={option}", *extra])
    validate(cfg)
    expected = OmegaConf.load(Path(CONF_DIR) / group / f"{option}.yaml")
    for key, value in expected.items():
        if f"{group}.{key}" not in {e.split("=")[0] for e in extra}:
            assert cfg[group][key] == value, (group, option, key)


@pytest.mark.parametrize("preset", PRESETS)
def test_every_preset_composes_and_sweeps_valid_jobs(preset):
    from hydra.core.override_parser.overrides_parser import OverridesParser

    cfg = compose_config([f"experiment={preset}"], hydra=True)
    assert cfg.name == preset and cfg.hydra.job.chdir is False
    params = [f"{k}={v}" for k, v in cfg.hydra.sweeper.params.items()]
    jobs = sweep_jobs(OverridesParser.create().parse_overrides(params))
    assert len(jobs) >= 2
    for job in jobs[:: max(1, len(jobs) // 4)]:
        validate(compose_config([f"experiment={preset}", *job]))


def test_fig3_preset_is_the_papers_grid():
    from hydra.core.override_parser.overrides_parser import OverridesParser

    cfg = compose_config(["experiment=fig3"], hydra=True)
    sweep = OverridesParser.create().parse_overrides([f"{k}={v}" for k, v in cfg.hydra.sweeper.params.items()])
    cells = {tuple(float(o.split("=")[1]) for o in job) for job in sweep_jobs(sweep)}
    assert cells == {(n, ov, snr) for n in (10, 20) for ov in (0.75, 0.5) for snr in range(0, 45, 5)}
    # 10,000 trials per curve as in the paper, on both cores: cells as parallel jobs.
    assert cfg.mc.n_trials == 10000
    assert "joblib" in cfg.hydra.launcher._target_ and cfg.hydra.launcher.n_jobs == -1 and cfg.mc.n_jobs == 1


@pytest.mark.parametrize(
    "override, key",
    [
        ("scenario.overlap=1.5", "scenario.overlap"),
        ("scenario.overlap=0", "scenario.overlap"),
        ("scenario.n_landmarks=2", "scenario.n_landmarks"),
        ("mc.n_jobs=0", "mc.n_jobs"),
        ("mc.chunk_size=0", "mc.chunk_size"),
        ("matcher.taus=[chi2:2]", "matcher.taus"),
        ("+scenario.snrdb=30", "scenario.snrdb"),
        ("scenario.n_landmarks=4 scenario.overlap=0.5", "scenario.overlap"),
        ("scenario.snr_db=inf", "scenario.snr_db"),
        ("scenario.snr_db=2000", r"scenario.snr_db.*must be a number of dB in \[-300, 300\]"),
        ("scenario.aspect=0", "scenario.aspect"),
        ("scenario.p_detect=0", "scenario.p_detect"),
        ("scenario.clutter=-1", "scenario.clutter"),
        ("scenario.anisotropy=nan", "scenario.anisotropy"),
        ("scenario.anisotropy=1e9", r"scenario.anisotropy.*must be in \[0, 1000\]"),
        ("scenario.aspect=1e300", r"scenario.aspect.*must be in \[0.001, 1000\]"),
        ("scenario.n_landmarks=100000000", r"must keep n_landmarks \* \(1 \+ clutter\) at most 1,000,000"),
        ("scenario.clutter=1e9", r"scenario.n_landmarks=100 is invalid: .* \(clutter 1000000000.0\)"),
        ("matcher.taus=[]", "matcher.taus"),
        ("matcher.taus=[oracle,oracle]", "matcher.taus"),
        ("mc.n_trials=0", "mc.n_trials"),
        ("mc.seed=-1", "mc.seed"),
        ("mc.address=tcp://host:8786", "mc.address"),
        ("mc.n_trials=5 mc.examples=6", "mc.examples"),
        ("scenario=victoria_park scenario.cut=0", "scenario.cut"),
        ("scenario=victoria_park mc.n_trials=2", "mc.n_trials"),
    ],
)
def test_validate_names_the_key(override, key):
    with pytest.raises(ConfigError, match=key):
        validate(compose_config(override.split()))


@pytest.mark.parametrize(
    "override, allowed",
    [
        ("matcher.method=papr", "[paper, cyclic, consensus, consensus_count, search, groth, astroalign"),
        ("matcher.objective=max", "[lr, loglr]"),
        ("mc.backend=spark", "[loky, dask]"),
        ("scenario.kind=lidar", "[synthetic, victoria_park]"),
        ("scenario.layout=grid", "[strip, interleaved]"),
        ("scenario.source=lidar", "[reference, slam]"),
    ],
)
def test_a_choice_outside_its_values_is_refused_at_composition_with_them_listed(override, allowed):
    from hydra.errors import ConfigCompositionException

    with pytest.raises(ConfigCompositionException) as info:
        compose_config([override])
    key, value = override.split("=")
    assert f"Invalid value '{value}', expected one of {allowed}" in str(info.value.__cause__)
    assert f"full_key: {key}" in str(info.value.__cause__)


def test_validate_returns_the_typed_config_and_its_range_checks_run_in_the_dataclasses():
    from experiments.schema import Config, MCConfig, Method

    cfg = validate(compose_config(["matcher.method=consensus"]))
    assert isinstance(cfg, Config) and cfg.matcher.method is Method.consensus and cfg.matcher.method == "consensus"
    with pytest.raises(ConfigError, match=r"mc.chunk_size=0 is invalid: must be >= 1"):
        MCConfig(chunk_size=0)


@pytest.mark.parametrize(
    "args, message",
    [
        (["scenario.overlap=1.5"], ["scenario.overlap=1.5 is invalid: must be in (0, 1]"]),
        (["-m", "scenario.n_landmarks=2,10"], ["scenario.n_landmarks"]),
        (["-m", "scenario.overlap=0.5,1.5"], ["scenario.overlap=1.5 is invalid"]),
        (["-m", "experiment=smoke", "mc.n_jobs=0"], ["mc.n_jobs"]),
        (["scenario.snrdb=30"], ["scenario.snrdb is not a config key; did you mean scenario.snr_db?"]),
        (["+scenario.snrdb=30"], ["scenario.snrdb is not a config key; did you mean scenario.snr_db?"]),
        (["matcher.tau=chi2:0.01"], ["matcher.tau is not a config key; did you mean matcher.taus?"]),
        (["scenario.snr_db=loud"], ["scenario.snr_db=loud", "could not be converted to Float"]),
        (["mc.n_trials=abc"], ["mc.n_trials=abc", "could not be converted to Integer"]),
        (["mc.progress=maybe"], ["mc.progress=maybe", "not a valid bool"]),
        (["-m", "experiment=smoke", "mc.n_jobs=2"], ["mc.n_jobs=2 is invalid: must be 1 under hydra/launcher=joblib"]),
        (["-m", "scenario.snr_db=10,nope"], ["scenario.snr_db=nope", "could not be converted to Float"]),
        (["scenario=lidar"], ["scenario/lidar", "paper", "small"]),
    ],
)
def test_invalid_overrides_fail_fast_and_write_nothing(tmp_path, args, message, monkeypatch, capsys):
    # The command's own entry point in this process (a fresh interpreter per case costs seconds each); the
    # two cases after this test run it as the real command.
    from experiments.run import cli as command

    if "experiment=smoke" in args and "mc.n_jobs=2" in args:
        args = [*args, "hydra/launcher=joblib"]
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", ["run", *args])
    with pytest.raises(SystemExit) as exit_:
        command()
    assert exit_.value.code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:") and all(m in lines[0] for m in message), lines
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    "args, message",
    [
        (["scenario.overlap=1.5"], ["scenario.overlap=1.5 is invalid: must be in (0, 1]"]),
        (["-m", "scenario.snr_db=10,nope"], ["scenario.snr_db=nope", "could not be converted to Float"]),
    ],
)
def test_the_command_refuses_an_invalid_run_or_sweep_in_one_line_and_writes_nothing(tmp_path, args, message):
    proc = cli(args, tmp_path)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:") and all(m in lines[0] for m in message), proc.stderr
    assert list(tmp_path.iterdir()) == []


def test_sweep_jobs_expand_as_hydra_launches_them():
    from hydra.core.override_parser.overrides_parser import OverridesParser

    # The preset's params first, then the command line's: a later value of a key replaces an earlier one.
    parsed = OverridesParser.create().parse_overrides(
        ["scenario.snr_db=20,40", "mc.progress=false", "scenario.snr_db=range(0,10,5)", "matcher.method=paper,groth"])
    assert sweep_jobs(parsed) == [[f"scenario.snr_db={s}", "mc.progress=False", f"matcher.method={m}"]
                                  for s in (0, 5) for m in ("paper", "groth")]


def test_a_sweep_not_preflighted_is_still_checked_before_any_job_runs(tmp_path):
    # Hydra's main without the command line's preflight: the sweeper must check every job itself.
    code = ("import sys; from experiments.run import main; "
            "sys.argv = ['run', '-m', 'experiment=smoke', 'scenario.snr_db=20,loud', 'hydra.sweep.dir=out']; main()")
    proc = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env={**os.environ, "PYTHONPATH": str(ROOT)},
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode != 0 and "loud" in proc.stderr
    assert not list(tmp_path.rglob("trials.parquet"))


def test_a_launcher_whose_extra_is_missing_is_named_in_one_line(tmp_path):
    import importlib.util

    if importlib.util.find_spec("hydra_plugins.hydra_submitit_launcher") is not None:
        pytest.skip("the submitit launcher is installed")
    proc = cli(["-m", "hydra/launcher=submitit_slurm", "mc.n_trials=2"], tmp_path)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and "pip install 'mapmerge[launchers]'" in lines[0], proc.stderr
    assert list(tmp_path.iterdir()) == []

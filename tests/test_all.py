"""experiments.all: its steps, their selection, a dry run, the stop at a failing step, and that every
results/ folder is some step's (no driver is run here)."""

import shutil
import subprocess
from pathlib import Path

import pytest

from experiments import all as run_all

ROOT = Path(__file__).resolve().parent.parent


def names(steps):
    return [s.name for s in steps]


def test_steps_run_the_detector_before_its_readers_and_the_docs_last():
    steps = names(run_all.STEPS)
    assert len(set(steps)) == len(steps)
    last_detector = max(i for i, s in enumerate(run_all.STEPS) if s.args[0] == "experiments.detector")
    readers = [i for i, s in enumerate(run_all.STEPS) if s.args[0] in ("experiments.compare", "experiments.peers")]
    assert readers and last_detector < min(readers)
    assert steps[-1] == "docs"
    for step in run_all.STEPS:
        assert step.command.startswith("python -m experiments.")
        assert set(step.needs) <= set(run_all.INSTALL), step.name
    by_name = {s.name: s for s in run_all.STEPS}
    assert by_name["detector_small"].command == (
        "python -m experiments.detector --landmarks 10 20 --snrs 15 20 25 30 --layouts strip --trials 500 "
        "--null-pairs 10000 --false-alarm 1e-3 --maximiser pairs --out results/detector/small")
    assert {"pycpd", "clipperpy", "teaserpp_python"} <= set(by_name["peers"].needs)


def test_only_and_skip_keep_the_fixed_order_and_refuse_unknown_names(capsys):
    assert names(run_all.select(run_all.STEPS, only="docs,bent,paper")) == ["paper", "bent", "docs"]
    skipped = run_all.select(run_all.STEPS, skip="bench, team")
    assert names(skipped) == [n for n in names(run_all.STEPS) if n not in ("bench", "team")]
    assert names(run_all.select(run_all.STEPS, only="bent,sigma", skip="sigma")) == ["bent"]
    with pytest.raises(ValueError, match=r"--skip: unknown step\(s\) bnet; allowed: paper, detector, "):
        run_all.select(run_all.STEPS, skip="bnet")
    with pytest.raises(ValueError, match="leave no step"):
        run_all.select(run_all.STEPS, only="bent", skip="bent")
    assert run_all.main(["--only", "bent,nope"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "unknown step(s) nope; allowed: " + ", ".join(names(run_all.STEPS)) in err


def test_dry_run_and_list_print_the_commands_and_run_nothing(tmp_path, monkeypatch, capsys):
    def no_process(*args, **kwargs):
        raise AssertionError("a dry run started a process")

    monkeypatch.setattr(subprocess, "run", no_process)
    monkeypatch.chdir(tmp_path)
    assert run_all.main(["--dry-run", "--only", "detector_15db,peers"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("dry run, nothing is run: 2 of")
    assert "python -m experiments.detector --snrs 15 --layouts strip --trials 1000 --out results/detector/15db" \
        in out[1]
    assert out[2].split()[:4] == ["peers", "python", "-m", "experiments.peers"]
    if {s.name: s for s in run_all.STEPS}["peers"].skip_reason():  # the peers are not built here
        assert "# skipped: " in out[2]
    assert run_all.main(["--list"]) == 0
    assert [line.split()[0] for line in capsys.readouterr().out.splitlines()] == names(run_all.STEPS)
    assert not list(tmp_path.iterdir())


def test_a_run_skips_what_it_cannot_run_and_stops_at_the_first_failure(tmp_path, monkeypatch):
    monkeypatch.setitem(run_all.INSTALL, "no_such_module_here", "pip install nothing")
    steps = (run_all.Step("ok", ("json.tool", "--help"), ()),
             run_all.Step("absent", ("json.tool", "--help"), (), ("no_such_module_here",)),
             run_all.Step("broken", ("experiments.no_such_driver",), ()),
             run_all.Step("after", ("json.tool", "--help"), ()))
    timing = tmp_path / "timing.md"
    earlier = "| after | `python -m json.tool --help` | 12.0 | 2026-01-01 00:00 |"
    timing.write_text(f"| step | command | seconds | run |\n|---|---|---:|---|\n{earlier}\n")
    assert run_all.run_steps(list(steps), timing, steps) == 1
    rows = {line.split("|")[1].strip(): line for line in timing.read_text().splitlines() if line.startswith("| ")}
    assert float(rows["ok"].split("|")[3]) >= 0
    assert "skipped: no_such_module_here not installed (pip install nothing)" in rows["absent"]
    assert "failed (exit 1) after" in rows["broken"]
    assert rows["after"] == earlier  # not reached: its earlier row stays
    assert list(rows)[-1] == "total"


def test_every_results_folder_is_written_by_a_step():
    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.skip("needs the git checkout (its results/ files)")
    files = subprocess.run(["git", "ls-files", "--cached", "--others", "--exclude-standard", "results"],
                           cwd=ROOT, capture_output=True, text=True, check=True).stdout.split()
    folders = {Path(f).parent.as_posix() for f in files}
    written = {folder for step in run_all.STEPS for folder in step.writes}
    assert not folders - written, f"results folders no step writes: {sorted(folders - written)}"
    assert not written - folders, f"steps write folders missing from results/: {sorted(written - folders)}"

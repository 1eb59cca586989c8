"""Regenerate every committed result: each driver that writes results/, in one fixed order.

    python -m experiments.all                        # every step (make results)
    python -m experiments.all --list                 # the steps and their commands
    python -m experiments.all --only bent,sigma      # some steps
    python -m experiments.all --skip bench,team --dry-run   # what would run, running nothing

Run it from the project's root: the drivers write to ``results/`` below the
current directory. Each step is ``python -m experiments.<driver> ...`` in a
fresh process of this interpreter, the command a user would type, so no
step inherits another's imports or in-memory state (the disk caches are
shared: see docs/harness.md).

The order (``STEPS``) is the one the results depend on: the exhaustive
detector (``results/detector/``) comes before ``compare``, whose
``crossing.md`` and figure read its limit, and before ``peers``, whose table
lists it; ``docs`` comes last, since it copies the tables of ``results/``
into ``README.md`` and ``docs/*.md``. The rest is independent, and runs in
the order of the harness guide's table of drivers.

A step whose optional extra is not installed (``needs``; the peers come
from ``tools/build_peers.sh``) is skipped, not failed: it prints
``skipped: <reason>`` and so does its row of the timing table, because a
driver run without its extra would write a table short of that extra's
rows over the committed one. The first step that fails ends the run with
its exit status and its name.

After every step ``results/timing.md`` is written again: step, command and
wall seconds (or why it was skipped or how it failed), and when the run that
timed it started. A step this run did not select keeps its row from the
file, so a partial run leaves the other steps' last times in place.
"""

from __future__ import annotations

import argparse
import importlib.util
import shlex
import subprocess
import sys
import time
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

#: Where the timing table goes (relative to the project's root, like the drivers' outputs).
TIMING = Path("results") / "timing.md"

#: What installs each optional module a step may need.
INSTALL = {
    "astroalign": "pip install 'mapmerge[baselines]'",
    "gtsam": "pip install 'mapmerge[slam]'",
    "ortools": "pip install 'mapmerge[large]'",
    "pycpd": "pip install 'mapmerge[peers]'",
    "clipperpy": "tools/build_peers.sh",
    "teaserpp_python": "tools/build_peers.sh",
}


@dataclass(frozen=True)
class Step:
    """One driver run.

    Attributes
    ----------
    name : str
        What ``--only`` and ``--skip`` call it.
    args : tuple of str
        The arguments after ``python -m``.
    writes : tuple of str
        Every directory it writes files into, relative to the project's root.
    needs : tuple of str
        Modules beyond the harness it needs (keys of ``INSTALL``).
    """

    name: str
    args: tuple[str, ...]
    writes: tuple[str, ...]
    needs: tuple[str, ...] = ()

    @property
    def command(self) -> str:
        """The command as a user types it."""
        return shlex.join(["python", "-m", *self.args])

    def skip_reason(self) -> str | None:
        """Why the step cannot run here (its missing modules and how to get them), or None."""
        missing = [m for m in self.needs if importlib.util.find_spec(m) is None]
        if not missing:
            return None
        how = sorted({INSTALL[m] for m in missing})
        return f"{', '.join(missing)} not installed ({'; '.join(how)})"


def _compare(preset: str, needs: tuple[str, ...] = ()) -> Step:
    return Step(preset, ("experiments.compare", "--presets", preset), ("results/compare", f"results/compare/{preset}"),
                needs)


PEERS = ("pycpd", "clipperpy", "teaserpp_python")
#: Where the small-map checks write, and the cells of the levels, statistics and count checks: 10 and 20
#: landmarks, both layouts, 10-40 dB.
SMALL = "results/detector/small"
SMALL_CELLS = ("--landmarks", "10", "20", "--layouts", "strip", "interleaved", "--snrs", "10", "15", "20", "25", "30",
               "35", "40")
#: The same at every size of ``consensus.COUNT_LEVELS``.
COUNT_CELLS = ("--landmarks", "5", "10", "15", "20", "30", "50", *SMALL_CELLS[3:])


def _small_maps(name: str, *args: str) -> Step:
    """A step of ``experiments.small_maps`` on 2 workers, writing to ``SMALL``."""
    return Step(name, ("experiments.small_maps", *args, "--n-jobs", "2", "--out", SMALL), (SMALL,))


STEPS: tuple[Step, ...] = (
    Step("paper", ("experiments.paper",), ("results/paper", "results/paper/fig1", "results/paper/fig2",
                                            "results/paper/fig3")),
    Step("detector", ("experiments.detector",), ("results/detector",)),
    Step("detector_15db", ("experiments.detector", "--snrs", "15", "--layouts", "strip", "--trials", "1000",
                           "--out", "results/detector/15db"), ("results/detector/15db",)),
    # The paper's Fig. 3 map sizes at a 1e-3 false-alarm rate (docs/small_maps.md): 10,000 null pairs per cell.
    Step("detector_small", ("experiments.detector", "--landmarks", "10", "20", "--snrs", "15", "20", "25", "30",
                            "--layouts", "strip", "--trials", "500", "--null-pairs", "10000", "--false-alarm", "1e-3",
                            "--maximiser", "pairs", "--out", "results/detector/small"), ("results/detector/small",)),
    # Both read detector_small's stages.csv.
    _small_maps("small_bound", "--landmarks", "10", "20", "--snrs", "20", "30", "--checks", "bound", "--bound-pairs",
                "2000"),
    _small_maps("small_holdout", "--landmarks", "10", "20", "--snrs", "20", "30", "--checks", "holdout", "--pairs",
                "10000"),
    _small_maps("small_acceptance", "--landmarks", "5", "10", "15", "20", "30", "50", "100", "--layouts", "strip",
                "interleaved", "--snrs", "10", "15", "20", "25", "30", "35", "40", "--checks", "acceptance",
                "--tuning-pairs", "10000", "--related", "500", "--pairs", "10000"),
    # What-if levels of the triangle test on held-out pairs and on the peers' related pairs (docs/small_maps.md).
    _small_maps("small_levels", *SMALL_CELLS, "--checks", "levels", "--levels", "1e-4", "1e-3", "1e-2", "--related",
                "1000", "--pairs", "10000"),
    _compare("compare"),
    _compare("compare_consensus"),
    _compare("compare_search"),
    _compare("compare_astroalign", ("astroalign",)),
    _compare("compare_cpd", ("pycpd",)),
    _compare("compare_clipper", ("clipperpy",)),
    _compare("compare_teaser", ("teaserpp_python",)),
    _compare("compare_association"),
    Step("realistic", ("experiments.realistic",), ("results/realistic",)),
    Step("victoria", ("experiments.victoria",), ("results/victoria_park",), ("gtsam", "astroalign")),
    # bench.md and bench.csv sit in results/ itself.
    Step("bench", ("experiments.bench",), ("results", "results/bench"), ("ortools", "astroalign")),
    Step("sigma", ("experiments.sigma",), ("results/sigma",)),
    Step("bent", ("experiments.bent",), ("results/bent",)),
    Step("team", ("experiments.team",), ("results/team",)),
    Step("mrclam", ("experiments.mrclam",), ("results/mrclam",), ("gtsam",)),
    Step("peers_calibrate", ("experiments.peers", "--calibrate"), ("results/peers",), PEERS),
    Step("peers", ("experiments.peers",), ("results/peers",), (*PEERS, "astroalign")),
    Step("peers_interleaved", ("experiments.peers", "--layout", "interleaved"), ("results/peers",), PEERS),
    Step("peers_scaling", ("experiments.peers", "--scaling"), ("results/peers",), PEERS),
    # Each peer's bound set per cell (1,000 tuning pairs) so that every method is at one false-merge rate.
    Step("peers_equal_rate", ("experiments.peers", "--equal-rate"), ("results/peers",), PEERS),
    # The triangle test with its threshold set per cell as the peers' are, three rankings (docs/small_maps.md).
    _small_maps("small_statistics", *SMALL_CELLS, "--checks", "statistics", "--tuning-pairs", "10000", "--related",
                "1000", "--pairs", "10000"),
    # consensus_count's levels per map size (consensus.COUNT_LEVELS), the search included, on tuning pairs.
    _small_maps("small_count_levels", *COUNT_CELLS, "--checks", "count_levels", "--tuning-pairs", "10000"),
    # consensus_count on held-out unrelated pairs and the peers' related pairs, every size it covers; the
    # held-out seeds start at 800000, as the levels at 1 tuning pair per 10,000 were chosen after checks
    # on seeds 600000+ and 700000+.
    _small_maps("small_count", *COUNT_CELLS, "--checks", "count", "--related", "1000", "--pairs", "10000",
                "--holdout-seed", "800000"),
    # The count test at the true transform beside consensus_count's finds: where its remaining power goes.
    _small_maps("small_oracle_count", "--landmarks", "10", "20", "--layouts", "strip", "interleaved", "--snrs", "15",
                "20", "25", "--checks", "oracle_count", "--related", "1000"),
    # Each peer with one bound per small-map size, as consensus_count has one level per size (10-40 dB).
    Step("peers_one_bound", ("experiments.peers", "--one-bound"), ("results/peers",), ("pycpd",)),
    # consensus and consensus_count beside the best peer (per cell and with one bound per size) and the detector.
    Step("small_reference", ("experiments.small_maps", "--checks", "reference", "--out", SMALL), (SMALL,)),
    Step("docs", ("experiments.docs",), ()),
)


def select(steps: tuple[Step, ...], only: str | None = None, skip: str | None = None) -> list[Step]:
    """The steps named by ``only`` (comma-separated; default all) less those named by ``skip``, in order.

    Raises
    ------
    ValueError
        On a name that is no step's, or when nothing is left.
    """
    names = [s.name for s in steps]
    chosen = set(names)
    for flag, value in (("--only", only), ("--skip", skip)):
        if value is None:
            continue
        given = {v.strip() for v in value.split(",") if v.strip()}
        unknown = sorted(given - set(names))
        if unknown:
            raise ValueError(f"{flag}: unknown step(s) {', '.join(unknown)}; allowed: {', '.join(names)}")
        chosen = given if flag == "--only" else chosen - given
    if not chosen:
        raise ValueError(f"--only/--skip leave no step to run; allowed: {', '.join(names)}")
    return [s for s in steps if s.name in chosen]


def timing_rows(path: Path) -> dict[str, str]:
    """The step rows of an earlier timing table, by step name (empty without one)."""
    if not path.exists():
        return {}
    rows = {}
    for line in path.read_text().splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if line.startswith("| ") and len(cells) == 4:
            rows[cells[0]] = line
    return rows


def write_timing(path: Path, steps: tuple[Step, ...], rows: dict[str, str], total: float, started: str) -> None:
    """The timing table: a row per step of ``steps`` that has one, then this run's total."""
    lines = ["# Wall time per step of `python -m experiments.all`", "",
             "Each step in a fresh process; the file is written again after every step. A step the last run "
             "did not select keeps the row of the run that timed it (`run`: when that run started, UTC).", "",
             "| step | command | seconds | run |", "|---|---|---:|---|"]
    lines += [rows[s.name] for s in steps if s.name in rows]
    lines.append(f"| total | this run's steps | {total:.0f} | {started} |")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")


def run_steps(chosen: list[Step], timing: Path = TIMING, steps: tuple[Step, ...] = STEPS) -> int:
    """Run ``chosen`` in order, each ``python -m ...`` in a fresh process, writing ``timing`` after each.

    Returns
    -------
    int
        0, or the exit status of the first step that failed (which ends the run).
    """
    from .paper import run_module  # pandas and matplotlib: only when something runs

    started = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M")
    rows = timing_rows(timing)
    total = 0.0
    for i, step in enumerate(chosen, 1):
        print(f"== [{i}/{len(chosen)}] {step.name}: {step.command}", flush=True)
        reason = step.skip_reason()
        if reason is not None:
            print(f"== {step.name}: skipped: {reason}", flush=True)
            rows[step.name] = f"| {step.name} | `{step.command}` | skipped: {reason} | {started} |"
            write_timing(timing, steps, rows, total, started)
            continue
        clock = time.perf_counter()
        try:
            run_module(list(step.args))
            code = 0
        except subprocess.CalledProcessError as exc:
            code = exc.returncode if exc.returncode > 0 else 1  # killed by a signal: still a failure
        seconds = time.perf_counter() - clock
        total += seconds
        outcome = f"{seconds:.1f}" if code == 0 else f"failed (exit {code}) after {seconds:.1f}"
        rows[step.name] = f"| {step.name} | `{step.command}` | {outcome} | {started} |"
        write_timing(timing, steps, rows, total, started)
        print(f"== {step.name}: {outcome} s", flush=True)
        if code:
            print(f"experiments.all: step {step.name} failed (exit {code}): {step.command}", file=sys.stderr)
            return code
    print(f"== {len(chosen)} steps in {total:.0f} s; times in {timing}", flush=True)
    return 0


def describe(chosen: list[Step]) -> str:
    """One line per step: its name, command and, if it cannot run here, why (``--list``, ``--dry-run``)."""
    width = max(len(s.name) for s in chosen)
    lines = []
    for step in chosen:
        reason = step.skip_reason()
        lines.append(f"{step.name:<{width}}  {step.command}" + (f"  # skipped: {reason}" if reason else ""))
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description="Regenerate every committed result (each driver in turn).")
    parser.add_argument("--only", help="comma-separated steps to run (default: every step)")
    parser.add_argument("--skip", help="comma-separated steps not to run")
    parser.add_argument("--list", action="store_true", help="print every step and its command, run nothing")
    parser.add_argument("--dry-run", action="store_true", help="print the steps that would run, run nothing")
    args = parser.parse_args(argv)
    try:
        chosen = select(STEPS, args.only, args.skip)
    except ValueError as exc:
        print(f"experiments.all: {exc}", file=sys.stderr)
        return 2
    if args.list or args.dry_run:
        if args.dry_run:
            print(f"dry run, nothing is run: {len(chosen)} of {len(STEPS)} steps, in this order")
        print(describe(list(STEPS) if args.list else chosen))
        return 0
    if not Path("results").is_dir():
        print("experiments.all: no results/ here: run it from the project's root", file=sys.stderr)
        return 2
    return run_steps(chosen)


if __name__ == "__main__":
    raise SystemExit(main())

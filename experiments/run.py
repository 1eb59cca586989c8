"""Run the Monte Carlo trials of one grid cell (Hydra app).

    python -m experiments.run [overrides]              # one cell
    python -m experiments.run -m experiment=fig3       # a sweep preset
    python -m experiments.run -m scenario.snr_db=20,30,40

Each run writes into its Hydra output directory (its chunks of trials go
to the trial cache, ``<output_root>/cache/trials/<key>/``, one atomic
Parquet file per finished chunk: the resume points, shared by every run and
sweep of the same cell, so that more trials compute only the new ones):

- ``trials.parquet``: one row per trial and τ rule (counts, map-level errors);
- ``pairs.parquet``: one row per tentative triangle pair (score, label);
- ``timings.parquet``: per-trial timings (kept apart: they vary run to run,
  while the two files above are bit-identical for any ``n_jobs``,
  ``chunk_size`` and after a resume);
- ``summary_*.parquet``: the run's rows of the aggregate tables (see
  ``experiments.aggregate``);
- ``results.parquet``: its rows of the results store (``experiments.results``),
  also written to ``<output_root>/results/``;
- ``config.yaml`` (resolved) and, with ``mc.examples > 0``, the geometry of
  the first trials for Fig. 1 and Fig. 2.

Rerunning the same command, or one with a larger ``mc.n_trials``, skips
finished chunks. Every config value is checked, for every job of a sweep,
before Hydra creates any directory.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import socket
import sys
from contextlib import contextmanager
from pathlib import Path

import hydra
from omegaconf import DictConfig, OmegaConf

from . import progress
from .preflight import preflight
from .schema import CONF_DIR, ConfigError, register_configs, validate

# The Monte Carlo machinery (numpy, scipy, pandas, pyarrow, joblib) is imported
# where it is used, so that the command line refuses a bad override quickly.

log = logging.getLogger(__name__)


def dirname(overrides: str) -> str:
    """A run directory name from Hydra's ``override_dirname``: its escapes
    dropped and ':' (from τ rules such as chi2:0.01) written as '-'."""
    return overrides.replace("\\", "").replace(":", "-") or "defaults"


def sweep_name(name: str, now: str) -> str:
    """A sweep's directory below ``sweeps/``: its ``name``, or for the unnamed default ``default/<now>``, so
    that sweeps without ``name=`` do not pool into one aggregate."""
    return f"{name}/{now}" if name == UNNAMED else name


#: The value of ``name`` when none is given.
UNNAMED = "default"

OmegaConf.register_new_resolver("dirname", dirname, replace=True)
OmegaConf.register_new_resolver("sweep_name", sweep_name, replace=True)
register_configs()


def write_parquet_atomic(df, path: Path) -> None:
    """Write a DataFrame as a Parquet file that either exists complete or not at all."""
    import pyarrow as pa

    _write_table_atomic(pa.Table.from_pandas(df, preserve_index=False), path)


def _write_table_atomic(table, path: Path) -> None:
    import pyarrow.parquet as pq

    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    # Plain encoding: dictionary pages save little on these tables (scores and
    # errors are all distinct) and cost a third of the write, once per trial.
    pq.write_table(table, tmp, use_dictionary=False)
    os.replace(tmp, path)


def _run_key(cfg: DictConfig) -> str:
    """Hash of everything that determines the trials' content, the code, numpy's and scipy's
    versions and the machine's arithmetic included (a chunk left by an older version of the
    library or of numpy or scipy, or computed where numpy's transcendental functions give other
    bits, is never reused)."""
    from .trials import arithmetic_digest, code_digest, library_versions

    key = {
        "scenario": OmegaConf.to_container(cfg.scenario, enum_to_str=True),
        "matcher": OmegaConf.to_container(cfg.matcher, enum_to_str=True),
        "seed": cfg.mc.seed,
        "code": code_digest(),
        "arithmetic": arithmetic_digest(),
        "libraries": library_versions(),
    }
    return hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:12]


@contextmanager
def _backend(mc, n_chunks: int):
    """joblib backend: local loky processes (none for a single chunk: starting
    workers costs more than half a second), or a dask.distributed cluster."""
    import joblib

    if mc.backend == "loky":
        with joblib.parallel_config(backend="loky", n_jobs=min(mc.n_jobs, n_chunks)):
            yield
        return
    from dask.distributed import Client, LocalCluster

    if mc.address:
        client = Client(mc.address)
        cluster = None
    else:
        cluster = LocalCluster(n_workers=mc.n_jobs, threads_per_worker=1, processes=True)
        client = Client(cluster)
    try:
        with joblib.parallel_config(backend="dask", n_jobs=mc.n_jobs):
            yield
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def run(cfg: DictConfig, output_dir: str | Path, cache_dir: str | Path | None = None,
        store_dir: str | Path | None = None) -> Path:
    """Run (or resume, or extend) the trials of one cell and write its result files.

    Parameters
    ----------
    cfg : DictConfig
        A composed config (see ``conf/``).
    output_dir : path
        Where the files go (the Hydra output directory).
    cache_dir : path, optional
        The trial cache: chunks of trials by ``_run_key`` (scenario, matcher, seed, code, library
        versions and arithmetic), reused by any run of the same cell, whatever its ``n_trials``.
        ``python -m experiments.run`` passes ``<output_root>/cache/trials`` (shared by runs and
        sweeps); by default ``<output_dir>/chunks``.
    store_dir : path, optional
        The results store (``experiments.results``) that gets this run's rows, besides its own
        ``results.parquet``; ``python -m experiments.run`` passes ``<output_root>/results``.

    Returns
    -------
    Path
        The ``trials.parquet`` written.
    """
    validate(cfg)
    import pyarrow as pa
    import pyarrow.parquet as pq

    from .aggregate import SUMMARIES, run_summaries, summary_path
    from .examples import example_tables
    from .results import RUN_FILE, run_rows, store_file
    from .trials import cell_key

    out = Path(output_dir)
    out.mkdir(parents=True, exist_ok=True)
    run_key = _run_key(cfg)
    chunk_dir = Path(out / "chunks" if cache_dir is None else cache_dir) / run_key
    chunk_dir.mkdir(parents=True, exist_ok=True)
    OmegaConf.save(cfg, out / "config.yaml", resolve=True)

    # Plain values (the enums' names) for the trials, the cache key and the result files.
    scenario = OmegaConf.to_container(cfg.scenario, enum_to_str=True)
    matcher = OmegaConf.to_container(cfg.matcher, enum_to_str=True)
    n, seed = cfg.mc.n_trials, cfg.mc.seed

    def stem(a, b):
        return chunk_dir / f"{a:07d}_{b:07d}"

    pieces, missing = cover(cached_chunks(chunk_dir), n)
    n_missing = sum(b - a for a, b in missing)
    # chunk_size is an upper bound: every worker gets at least one chunk.
    size = min(cfg.mc.chunk_size, -(-n_missing // cfg.mc.n_jobs)) if n_missing else 1
    todo = [(a, min(a + size, b)) for lo, b in missing for a in range(lo, b, size)]
    pieces = sorted(pieces + [(a, b, a, b) for a, b in todo], key=lambda piece: piece[2])
    log.info(
        "cell %s: %d trials, %d cached, %d to run in %d chunks, n_jobs=%d backend=%s",
        scenario, n, n - n_missing, n_missing, len(todo), cfg.mc.n_jobs, str(cfg.mc.backend),
    )
    progress.cell_started(n - n_missing)
    fresh = {}  # the chunks this process computed or received, kept rather than read back
    if todo:
        try:
            fresh = _run_chunks(cfg, scenario, matcher, todo, stem)
        except KeyboardInterrupt:
            pass  # joblib may also end its results early when Ctrl-C reaches the workers
        done = sum(Path(f"{stem(a, b)}.trials.parquet").exists() for a, b in todo)
        if done < len(todo):
            print(f"interrupted: {done} of {len(todo)} chunks saved in {chunk_dir}; "
                  "rerun the same command to resume", file=sys.stderr)
            raise SystemExit(130)

    cell = {**scenario, "method": matcher["method"], "objective": matcher["objective"],
            "use_cov": matcher["use_cov"], "seed": seed, "cell_key": cell_key(scenario)}
    # Summaries of older files must not outlive them.
    for kind in SUMMARIES:
        summary_path(out, kind).unlink(missing_ok=True)
    # Arrow tables straight through: this runs once per cell while the
    # workers wait, so it avoids pandas round trips.
    tables = {}
    for kind in ("trials", "pairs", "timings"):
        parts = [fresh[a, b][kind] if (a, b) in fresh else pq.read_table(f"{stem(a, b)}.{kind}.parquet")
                 for a, b, _, _ in pieces]
        table = pa.concat_tables([_trials_between(part, lo, hi) if (lo, hi) != (a, b) else part
                                  for part, (a, b, lo, hi) in zip(parts, pieces)])
        if kind == "trials":
            n_rows = table.num_rows
            for i, (key, value) in enumerate(cell.items()):
                table = table.add_column(i, key, pa.repeat(value, n_rows))
        _write_table_atomic(table, out / f"{kind}.parquet")
        tables[kind] = table
    summaries = run_summaries(out, tables["trials"], tables["timings"], tables["pairs"])
    for kind, summary in summaries.items():
        _write_table_atomic(summary, summary_path(out, kind))
    rows = pa.Table.from_pandas(run_rows(cfg, out, tables["trials"].to_pandas(),
                                         {kind: t.to_pandas() for kind, t in summaries.items()}, run_key),
                                preserve_index=False)
    _write_table_atomic(rows, out / RUN_FILE)
    if store_dir is not None:
        Path(store_dir).mkdir(parents=True, exist_ok=True)
        _write_table_atomic(rows, store_file(store_dir, out))
    if cfg.mc.examples:
        for name, table in example_tables(seed, scenario, matcher, range(cfg.mc.examples)).items():
            write_parquet_atomic(table, out / f"{name}.parquet")
    log.info("wrote %s (%d rows)", out / "trials.parquet", n_rows)
    return out / "trials.parquet"


def cached_chunks(chunk_dir: Path) -> list[tuple[int, int]]:
    """The (start, stop) trial ranges of the finished chunks in ``chunk_dir`` (its trials file, written
    last, marks a chunk finished)."""
    chunks = []
    for path in chunk_dir.glob("*.trials.parquet"):
        a, _, b = path.name.removesuffix(".trials.parquet").partition("_")
        if a.isdigit() and b.isdigit():
            chunks.append((int(a), int(b)))
    return chunks


def cover(chunks, n: int) -> tuple[list[tuple[int, int, int, int]], list[tuple[int, int]]]:
    """Trials ``0..n-1`` from cached chunks: the pieces to read and the ranges to compute.

    Parameters
    ----------
    chunks : iterable of (int, int)
        Cached chunks' trial ranges (``start``, ``stop``), which may overlap or go past ``n``.
    n : int
        Trials wanted.

    Returns
    -------
    pieces : list of (a, b, lo, hi)
        Chunk ``(a, b)`` supplies trials ``lo..hi-1``; in trial order, not overlapping.
    missing : list of (lo, hi)
        The ranges of trials no chunk holds.
    """
    chunks = sorted(set(chunks))
    pieces, missing, pos = [], [], 0
    while pos < n:
        holding = [(a, b) for a, b in chunks if a <= pos < b]
        if holding:
            a, b = max(holding, key=lambda chunk: chunk[1])  # the chunk reaching furthest
            pieces.append((a, b, pos, min(b, n)))
            pos = min(b, n)
        else:
            stop = min([a for a, _ in chunks if a > pos] + [n])
            missing.append((pos, stop))
            pos = stop
    return pieces, missing


def _trials_between(table, lo: int, hi: int):
    """The rows of trials ``lo..hi-1`` of a chunk's table."""
    import pyarrow.compute as pc

    trial = table.column("trial")
    return table.filter(pc.and_(pc.greater_equal(trial, lo), pc.less(trial, hi)))


def _run_chunks(cfg, scenario: dict, matcher: dict, todo, stem) -> dict:
    """Run the missing chunks on the configured backend, each saved as it finishes.

    Returns the tables of the chunks computed in this process or shipped to
    it (by ``(start, stop)``), which need not be read back from their files.
    """
    import joblib
    from tqdm.auto import tqdm

    from .trials import arithmetic_digest

    seed = cfg.mc.seed
    # Local workers write their own chunks (no DataFrames shipped back);
    # dask workers may sit on other machines, so the driver writes theirs.
    local = cfg.mc.backend == "loky"
    fresh = {}
    with _backend(cfg.mc, len(todo)):
        jobs = (joblib.delayed(_chunk_job)(seed, scenario, matcher, a, b, stem(a, b) if local else None, os.getpid(),
                                           arithmetic_digest())
                for a, b in todo)
        results = joblib.Parallel(return_as="generator_unordered")(jobs)
        # Below the sweep's overall bar, when there is one, and gone when the cell is done.
        with tqdm(
            total=sum(b - a for a, b in todo), unit="trial", desc=f"{cfg.name}",
            disable=not progress.enabled(cfg.mc.progress), file=sys.stderr,
            position=1 if progress.active() else None, leave=not progress.active(),
        ) as bar:
            for a, b, frames, tables in results:
                if frames is not None:
                    tables = _write_chunk(stem(a, b), *frames)
                if tables is not None:
                    fresh[a, b] = tables
                bar.update(b - a)
                progress.trials_done(b - a)
    return fresh


def _chunk_job(seed, scenario, matcher, a, b, base: Path | None, driver: int, arithmetic: str):
    """Run one chunk; write it when ``base`` is given, else return its frames. Its written
    tables come back only to the ``driver`` process itself (n_jobs=1), never across processes.
    ``arithmetic``: the driver's ``arithmetic_digest``, which this worker's must equal."""
    from .trials import arithmetic_digest, run_chunk

    if arithmetic_digest() != arithmetic:
        raise RuntimeError(f"worker {socket.gethostname()} computes numpy's sin/cos/exp/log/arctan2 with other bits "
                           "than the driver (e.g. AVX-512 kernels on one only), so results would depend on which "
                           "worker ran which chunk: use workers of one CPU type")
    frames = run_chunk(seed, scenario, matcher, a, b)
    if base is None:
        return a, b, frames, None
    tables = _write_chunk(base, *frames)
    return a, b, None, tables if os.getpid() == driver else None


def _write_chunk(base: Path, trials, pairs) -> dict:
    """Write one chunk's three files; returns the tables written, by kind."""
    import pyarrow as pa

    from .trials import TIME_COLUMNS

    # One conversion from pandas; the trials and timings files are column selections of it.
    table = pa.Table.from_pandas(trials, preserve_index=False)
    tables = {"pairs": pa.Table.from_pandas(pairs, preserve_index=False),
              "timings": table.select(["trial", "tau", *TIME_COLUMNS]),
              "trials": table.drop_columns(list(TIME_COLUMNS))}
    # The trials file last: its presence marks the chunk done.
    for kind in ("pairs", "timings", "trials"):
        _write_table_atomic(tables[kind], Path(f"{base}.{kind}.parquet"))
    return tables


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="config")
def main(cfg: DictConfig) -> None:
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    from .results import STORE

    progress.set_quiet(HydraConfig.get().overrides.hydra)
    root = Path(cfg.output_root)
    path = run(cfg, HydraConfig.get().runtime.output_dir, cache_dir=root / "cache" / "trials",
               store_dir=root / STORE)
    if HydraConfig.get().mode == RunMode.RUN:  # a sweep's numbers come from its aggregate
        import pandas as pd

        print(headline(pd.read_parquet(path)))


def headline(trials) -> str:
    """One run's numbers per τ rule: detections, P_D / P_FA, merges."""
    from .aggregate import markdown, summary_table

    cols = {"tau": "τ rule", "n_trials": "trials", "tp": "TP", "fp": "FP", "md": "MD", "precision": "precision",
            "p_d": "P_D", "p_fa": "P_FA", "success_rate": "merge success", "false_merge_rate": "false merges"}
    table = summary_table(trials.assign(time_match_s=0.0, time_merge_s=0.0))
    return markdown(table[list(cols)].rename(columns=cols))


def cli() -> None:
    passthrough = {"--help", "-h", "--hydra-help", "--info", "-i", "--cfg", "-c", "--resolve",
                   "--shell-completion", "-sc", "--config-path", "-cp", "--config-name", "-cn",
                   "--config-dir", "-cd", "--experimental-rerun"}
    if not passthrough.intersection(sys.argv[1:]):
        try:
            progress.plan(preflight(sys.argv[1:]))
        except ConfigError as exc:
            print(f"error: {exc}", file=sys.stderr)
            raise SystemExit(2) from None
    main()


if __name__ == "__main__":
    cli()

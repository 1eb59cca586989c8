"""Bent maps: does ``residual_match`` tell a map that is not one rigid body? (results/bent/table.md)

    python -m experiments.bent            # about 2 minutes on 2 cores

Map pairs of the synthetic scenario (100 landmarks per map, 75 % common),
merged by ``consensus``; every matched merge goes to ``residual_match``,
which runs ``consensus`` again on the landmarks the merge left unpaired.

- Rigid pairs (seeds 700000 + k; strip, interleaved, interleaved with 20 %
  clutter; 15, 20, 30 dB): a second match is a false alarm.
- Bent pairs (seeds 710000 + k; strip and interleaved, 20 dB): map q bent
  by ``simulate.bend`` (the 40 % of its landmarks farthest towards the
  overlap turned by 2-16° about a hinge, so that the turned part is common
  landmarks, the part a merge can see bent). Reported:
  how often the second match is found, how far its rotation against the
  first is from the bend, and its share of correct pairs (same landmark id),
  with the bend's largest landmark displacement in units of σ.

Nothing here is tuned: ``residual_match`` has no constant of its own (its
acceptance is ``consensus``'s).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pandas as pd
from joblib import Parallel, delayed

import mapmerge as mm

from .aggregate import save_table

RIGID_SEED, BENT_SEED = 700000, 710000
RIGID_CELLS = [(layout, clutter, snr) for layout, clutter in (("strip", 0.0), ("interleaved", 0.0),
                                                             ("interleaved", 0.2)) for snr in (15.0, 20.0, 30.0)]
BENT_CELLS = [(layout, 0.0, 20.0, angle) for layout in ("strip", "interleaved") for angle in (2.0, 4.0, 8.0, 16.0)]
BENT_FRACTION = 0.4


def cell(layout: str, clutter: float, snr_db: float, bend_deg: float, n_pairs: int) -> dict:
    """Merges and residual matches of ``n_pairs`` pairs of one cell (``bend_deg`` 0: rigid)."""
    seed0 = BENT_SEED if bend_deg else RIGID_SEED
    matched = found = 0
    offset_err, correct_share, displacement = [], [], []
    for k in range(n_pairs):
        sc = mm.simulate.make_pair(100, 0.75, snr_db, rng=seed0 + k, layout=layout, clutter=clutter)
        q = sc.q
        if bend_deg:
            towards_overlap = sc.q[np.isin(sc.ids_q, sc.ids_p)].mean(axis=0) - sc.q.mean(axis=0)
            q = mm.simulate.bend(sc.q, np.radians(bend_deg), BENT_FRACTION, towards_overlap)
            displacement.append(np.linalg.norm(q - sc.q, axis=1).max() / sc.sigma)
        first = mm.merge_maps(sc.p, q, sc.sigma)
        if not first.matched:
            continue
        matched += 1
        second = mm.residual_match(sc.p, q, first, sc.sigma)
        if second.matched:
            found += 1
            offset_err.append(abs(abs(np.degrees(second.rotation_offset)) - bend_deg))
            correct_share.append(np.mean(sc.ids_p[second.pairs[:, 0]] == sc.ids_q[second.pairs[:, 1]]))
    return {"pairs": "bent" if bend_deg else "rigid", "layout": layout, "clutter": clutter, "snr_db": snr_db,
            "bend_deg": bend_deg, "max_displacement_sigmas": float(np.median(displacement)) if displacement else 0.0,
            "n_pairs": n_pairs, "matched": matched, "second_match": found,
            "second_match_rate": found / matched if matched else np.nan,
            "median_offset_err_deg": float(np.median(offset_err)) if offset_err else np.nan,
            "correct_share": float(np.mean(correct_share)) if correct_share else np.nan}


def measure(n_pairs: int = 200, n_jobs: int = 2) -> pd.DataFrame:
    cells = [(*c, 0.0) for c in RIGID_CELLS] + BENT_CELLS
    rows = Parallel(n_jobs=n_jobs)(delayed(cell)(*c, n_pairs) for c in cells)
    return pd.DataFrame(rows)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description="residual_match on rigid and bent synthetic map pairs.")
    parser.add_argument("--out", default="results/bent")
    parser.add_argument("--pairs", type=int, default=200, help="map pairs per cell")
    parser.add_argument("--jobs", type=int, default=2)
    args = parser.parse_args(argv)
    if args.pairs < 1 or args.jobs < 1:
        raise SystemExit("--pairs and --jobs must be >= 1")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for path in save_table(measure(args.pairs, args.jobs), out / "table"):
        print(path)
    print((out / "table.md").read_text())


if __name__ == "__main__":
    main()

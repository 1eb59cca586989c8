"""The ``mapmerge`` command: merge two landmark map files.

    mapmerge merge A.csv B.csv --sigma 0.02 -o merged.csv [--plot merged.png] [--json]
    mapmerge merge A.csv B.csv -o merged.csv   # both files give covariances: σ pooled from them
    python -m mapmerge merge ...

Reads two maps (``mapmerge.mapfiles``), runs ``merge_maps`` (method
``consensus`` unless ``--method`` says otherwise) and writes the combined
map in map A's frame. After a match it looks for a second rigid match among the
landmarks left unpaired (``residual_match``) and warns when there is one:
the maps are then bent, and the combined map aligns only the larger part.
Exit status: 0 matched, 1 no match (nothing written), 2 bad input.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from . import __version__
from ._validation import check_points
from .mapfiles import MapFileError, read_map, write_map
from .merging import DEFAULT_TAU, METHODS, merge_maps, pooled_sigma, residual_match


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="mapmerge", description="Match and merge stochastic landmark maps.")
    parser.add_argument("--version", action="version", version=f"mapmerge {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    merge = sub.add_parser("merge", help="merge map B into map A's frame",
                           description="Merge map B into map A's frame and write the combined map. "
                                       "Map files: CSV or TSV with a header; columns x, y, optional id, "
                                       "optional covariance sxx, sxy, syy or sigma.")
    merge.add_argument("map_a", help="map p (CSV/TSV)")
    merge.add_argument("map_b", help="map q (CSV/TSV)")
    merge.add_argument("--sigma", type=float, default=None,
                       help="per-coordinate standard deviation of a landmark, in map units; needed unless both "
                            "maps give covariances, whose RMS per-coordinate standard deviation is then used")
    merge.add_argument("--method", default="consensus", choices=list(METHODS), metavar="METHOD",
                       help="matcher, default consensus: " + "; ".join(f"{m.name}: {m.summary}"
                                                                   for m in METHODS.values()))
    merge.add_argument("--tau", default=DEFAULT_TAU, help=f"threshold: chi2:P or a log-LR (default {DEFAULT_TAU})")
    merge.add_argument("-o", "--output", required=True, help="combined map file to write (.csv or .tsv)")
    merge.add_argument("--plot", help="also draw both maps in A's frame to this image (PNG/PDF)")
    merge.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    merge.add_argument("--seed", type=_seed, default=None,
                       help="seed of randomised methods (astroalign), an integer >= 0")
    return parser


def _seed(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be an integer >= 0, got {text!r}")
    return value


def summary(res) -> dict:
    """Matched, θ (radians), t and their standard deviations, pair and conflict counts."""
    out = {"matched": bool(res.matched), "method": res.method, "pairs": int(len(res.pairs)),
           "conflicts": int(res.n_conflicts)}
    if res.matched:
        std = np.sqrt(np.diag(res.alignment.cov))
        out.update(theta=float(res.theta), theta_std=float(std[0]), t=[float(v) for v in res.t],
                   t_std=[float(v) for v in std[1:]])
    return out


def check_outputs(args) -> None:
    """Refuse, before any work, outputs that cannot be written: a missing directory, an input file
    overwritten, a table format other than CSV/TSV, a plot format matplotlib cannot write."""
    inputs = {Path(name).resolve() for name in (args.map_a, args.map_b)}
    for option, name in (("--output", args.output), ("--plot", args.plot)):
        if name is None:
            continue
        path = Path(name)
        if not path.resolve().parent.is_dir():
            raise ValueError(f"{option}: directory {str(path.parent)!r} does not exist")
        if path.resolve() in inputs:
            raise ValueError(f"{option}: {name} is an input map; write the result to another file")
    if Path(args.output).suffix.lower() not in (".csv", ".tsv", ".txt"):
        raise ValueError(f"--output: {args.output} must end in .csv, .tsv (tab-separated) or .txt")
    if args.plot is not None:
        from matplotlib.figure import Figure

        formats = Figure().canvas.get_supported_filetypes()
        if Path(args.plot).suffix.lower().lstrip(".") not in formats:
            raise ValueError(f"--plot: {args.plot} must end in one of "
                             + ", ".join(f".{f}" for f in sorted(formats)))


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    try:
        check_outputs(args)
        map_p, map_q = read_map(args.map_a), read_map(args.map_b)
        for landmarks in (map_p, map_q):  # a map's geometry errors named by its file, not by P / Q
            check_points(landmarks.points, f"{landmarks.source}:")
        if (map_p.cov is None) != (map_q.cov is None):
            raise ValueError("give covariances (sxx, sxy, syy or sigma) in both maps or in neither")
        if args.sigma is None and map_p.cov is None:
            raise ValueError("--sigma is needed when the maps give no covariances (sxx, sxy, syy or sigma columns)")
        sigma = args.sigma if args.sigma is not None else pooled_sigma(map_p.cov, map_q.cov)
        res = merge_maps(map_p.points, map_q.points, sigma, tau=args.tau, method=args.method,
                         cov_p=map_p.cov, cov_q=map_q.cov, rng=args.seed)
    except (MapFileError, ValueError, ImportError) as exc:
        print(f"mapmerge: error: {exc}", file=sys.stderr)
        return 2
    info = {**summary(res), "sigma": float(sigma)}
    if not res.matched:
        info["output"] = None
        print(json.dumps(info) if args.json else
              f"no match: {args.map_b} could not be matched to {args.map_a} (method {res.method}); "
              "nothing written", file=sys.stdout if args.json else sys.stderr)
        return 1
    second = residual_match(map_p.points, map_q.points, res, sigma, args.tau, map_p.cov, map_q.cov)
    info["second_match"] = ({"pairs": int(len(second.pairs)),
                             "rotation_offset_deg": float(np.degrees(second.rotation_offset))}
                            if second.matched else None)
    try:
        info["output"] = str(write_map(res, args.output, map_p, map_q))
        if args.plot:
            from .plotting import plot_merge

            info["plot"] = str(plot_merge(res, map_p.points, map_q.points, args.plot))
    except OSError as exc:  # e.g. no permission to write
        print(f"mapmerge: error: cannot write {exc.filename or args.output}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(info))
    else:
        deg, deg_std = np.degrees(info["theta"]), np.degrees(info["theta_std"])
        print(f"matched ({res.method}): theta = {deg:.4f} ± {deg_std:.4f} deg, "
              f"t = ({info['t'][0]:.4f} ± {info['t_std'][0]:.4f}, {info['t'][1]:.4f} ± {info['t_std'][1]:.4f}) "
              f"[q ≈ R(theta) p + t]; {info['pairs']} landmark pairs, {info['conflicts']} "
              f"conflict{'' if info['conflicts'] == 1 else 's'}")
        if args.sigma is None:
            print(f"sigma = {info['sigma']:.6g} (RMS of the maps' own standard deviations)")
        print(f"combined map: {len(res.merged)} landmarks -> {info['output']}"
              + (f"; plot -> {info['plot']}" if args.plot else ""))
        if second.matched:
            print(f"warning: the landmarks left unpaired hold a second rigid match ({len(second.pairs)} pairs, "
                  f"rotated {np.degrees(second.rotation_offset):.2f} deg against the first): one map is bent, "
                  "so the combined map aligns only the larger matched part and holds the other part's common "
                  "landmarks twice" + ("" if res.method == "consensus" else
                                       f", or the {res.method} match is wrong"), file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())

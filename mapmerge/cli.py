"""The ``mapmerge`` command: merge two or more landmark map files.

    mapmerge merge A.csv B.csv --sigma 0.02 -o merged.csv [--plot merged.png] [--json]
    mapmerge merge A.csv B.csv -o merged.csv   # both files give covariances: σ pooled from them
    mapmerge merge A.csv B.csv C.csv ... --sigma 0.02 -o merged.csv   # a team: merge_many
    python -m mapmerge merge ...

Reads the maps (``mapmerge.mapfiles``), runs ``merge_maps`` on two
(method ``consensus_count`` unless ``--method`` says otherwise) and writes the
combined map in map A's frame; three or more go to ``merge_many`` (every
pair merged, cycles checked, one joint solution) and the fused map is
written in the frame of the first map placed. After a match it looks for a second rigid match among the
landmarks left unpaired (``residual_match``) and warns when there is one:
the maps are then bent, and the combined map aligns only the larger part.
Before merging it compares the maps' landmark spacings (the median distance
of a landmark to its nearest neighbour): maps in different units differ by
their ratio of units, two maps of one area in the same units by little
(``SCALE_FACTOR``). Beyond that factor it warns, or with ``--strict``
refuses. After a merge by a method without an acceptance test of its own
(``merging.UNTESTED_METHODS``) it warns when the landmark pairs do not agree
on the one fitted rigid motion (``merging.rigid_check``).

Exit status (``EXIT_*``): 0 matched (with three or more maps: at least two
placed; each map left out is a warning), 1 no match (nothing written), 2 bad
input, arguments or an output it cannot write, 3 an unexpected error (a bug:
one line asking for a report, never a traceback).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

from . import __version__
from ._validation import check_points
from .group import INCONSISTENT, merge_many
from .mapfiles import LandmarkMap, MapFileError, read_map, write_group, write_map
from .merging import (DEFAULT_METHOD, DEFAULT_TAU, METHODS, UNTESTED_METHODS, merge_maps, pooled_sigma, residual_match,
                      rigid_check)

#: Exit statuses: one meaning each.
EXIT_MATCHED, EXIT_NO_MATCH, EXIT_BAD_INPUT, EXIT_BUG = 0, 1, 2, 3
#: Two maps whose median nearest-neighbour spacings differ by more than this factor are probably in
#: different units (the ratio of units shows as the ratio of spacings). Measured on synthetic pairs of
#: one area in one unit (75 % overlap, 20 dB, seeds 700000-701999): 2 of 2,000 10-landmark pairs exceed
#: 3 (largest 5.0), none of 2,000 20-landmark pairs (largest 2.4), none of 300 realistic 100-landmark
#: pairs (largest 1.26); the Victoria Park agents' tree maps differ by at most 1.2x.
SCALE_FACTOR = 3.0
#: A merge by a method without an acceptance test is called probably wrong (not just some of its pairs)
#: when more than this share of its landmark pairs lie off its rigid motion: a correct merge puts each
#: beyond ``rigid_check``'s bound with probability ``RIGID_CHECK_P / K``, so a few off are wrong pairs,
#: a quarter or more a wrong motion.
WRONG_MERGE_SHARE = 0.25
#: Significant digits of a number printed without an uncertainty (or with a zero one).
PLAIN_DIGITS = 6


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="mapmerge", description="Match and merge stochastic landmark maps.")
    parser.add_argument("--version", action="version", version=f"mapmerge {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    merge = sub.add_parser("merge", help="merge map B (and C, ...) into map A's frame",
                           description="Merge map B into map A's frame and write the combined map; with three "
                                       "or more maps, merge them all into one (in the first placed map's frame). "
                                       "Map files: CSV or TSV with a header; columns x, y, optional id, "
                                       "optional covariance sxx, sxy, syy or sigma.")
    merge.add_argument("maps", nargs="+", metavar="MAP", help="two or more map files (CSV/TSV): A B [C ...]")
    merge.add_argument("--sigma", type=float, default=None,
                       help="per-coordinate standard deviation of a landmark, in map units; needed unless both "
                            "maps give covariances, whose RMS per-coordinate standard deviation is then used")
    merge.add_argument("--method", default=DEFAULT_METHOD, choices=list(METHODS), metavar="METHOD",
                       help=f"matcher, default {DEFAULT_METHOD}: " + "; ".join(f"{m.name}: {m.summary}"
                                                                   for m in METHODS.values()))
    merge.add_argument("--tau", default=DEFAULT_TAU, help=f"threshold: chi2:P or a log-LR (default {DEFAULT_TAU})")
    merge.add_argument("-o", "--output", required=True, help="combined map file to write (.csv or .tsv)")
    merge.add_argument("--plot", help="also draw both maps in A's frame to this image (PNG/PDF)")
    merge.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    merge.add_argument("--seed", type=_seed, default=None,
                       help="seed of randomised methods (astroalign), an integer >= 0")
    merge.add_argument("--strict", action="store_true",
                       help=f"refuse (exit 2) maps whose landmark spacings differ more than {SCALE_FACTOR:g}x "
                            "(probably different units) instead of warning")
    return parser


def _seed(text: str) -> int:
    try:
        value = int(text)
    except (ValueError, OverflowError):
        value = -1
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be an integer >= 0, got {text!r}")
    return value


def summary(res) -> dict:
    """Matched, θ (radians and degrees), t and their standard deviations, pair and conflict counts."""
    out = {"matched": bool(res.matched), "method": res.method, "pairs": int(len(res.pairs)),
           "conflicts": int(res.n_conflicts)}
    if res.matched:
        std = np.sqrt(np.diag(res.alignment.cov))
        out.update(theta=float(res.theta), theta_std=float(std[0]), theta_deg=float(np.degrees(res.theta)),
                   theta_std_deg=float(np.degrees(std[0])), t=[float(v) for v in res.t],
                   t_std=[float(v) for v in std[1:]])
    return out


#: The units of ``--json``'s numbers (its ``units`` field).
JSON_UNITS = {"theta": "rad", "theta_std": "rad", "theta_deg": "deg", "theta_std_deg": "deg", "t": "map units",
              "t_std": "map units", "sigma": "map units", "spacing": "map units",
              "rotation_offset_deg": "deg", "rigid_check.max_stat": "chi2 (2 dof)"}


def spacing(points: np.ndarray) -> float:
    """Median distance from a landmark to its nearest neighbour (distinct points: > 0)."""
    from scipy.spatial import cKDTree

    return float(np.median(cKDTree(points).query(points, k=2)[0][:, 1]))


def scale_check(maps: list[LandmarkMap], names: list[str]) -> tuple[dict, str | None]:
    """Each map's landmark spacing against the first map's: the ``--json`` record and a warning, or None.

    ``names``: how the messages call the maps (``"map a"``, ...)."""
    spacings = [spacing(m.points) for m in maps]
    ratios = [s / spacings[0] for s in spacings]
    record = {"spacing": spacings, "ratio": ratios, "factor": SCALE_FACTOR}
    worst = int(np.argmax([abs(math.log(r)) for r in ratios]))
    ratio = ratios[worst]
    if max(ratio, 1 / ratio) <= SCALE_FACTOR:
        return record, None
    how = f"{_factor(ratio)}x" if ratio >= 1 else f"1/{_factor(1 / ratio)} of"
    return record, (f"{names[worst]}'s landmarks are spaced {how} {names[0]}'s (median nearest-neighbour "
                    f"distance {spacings[worst]:.3g} against {spacings[0]:.3g}): are both in the same units? "
                    "A merge finds rigid motions only")


def _factor(ratio: float) -> str:
    """A ratio >= 1 as a reader takes it in: 3.28, 992, 1,210, 4.1e+09."""
    return f"{ratio:.3g}" if ratio < 100 else f"{ratio:,.0f}" if ratio < 1e7 else f"{ratio:.2g}"


def with_std(value: float, std: float) -> str:
    """``value ± std`` with the digits the uncertainty supports: std to 2 significant digits, value to the
    same decimal place (scientific notation where that would print many zeros)."""
    if not (math.isfinite(std) and std > 0):
        return f"{value:.{PLAIN_DIGITS}g}" + ("" if math.isnan(std) else f" ± {std:.2g}")
    lead = math.floor(math.log10(std)) - 1  # the decimal place of std's second digit
    top = math.floor(math.log10(abs(value))) if value else lead
    if -10 <= lead <= 0 and top < 12 and top - lead <= 17:
        return f"{value:.{-lead}f} ± {std:.{-lead}f}"
    if 0 < lead and top < 12:
        return f"{value:.0f} ± {std:.2g}"
    digits = min(16, max(1, top - lead))
    return f"{value:.{digits}e} ± {std:.1e}"


def check_outputs(args) -> None:
    """Refuse, before any work, outputs that cannot be written: a missing directory, an input file
    overwritten, a table format other than CSV/TSV, a plot format matplotlib cannot write."""
    inputs = {Path(name).resolve() for name in args.maps}
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


def read_maps(paths: list[str], sigma: float | None) -> tuple[list[LandmarkMap], float]:
    """The map files read and checked, and the σ to merge them with (``--sigma``, or pooled from the
    maps' covariances). Raises ``MapFileError``/``ValueError`` on bad input."""
    maps = [read_map(path) for path in paths]
    for landmarks in maps:  # a map's geometry errors named by its file, not by P / Q
        check_points(landmarks.points, f"{landmarks.source}:")
    if len({m.cov is None for m in maps}) > 1:
        raise ValueError("give covariances (sxx, sxy, syy or sigma) in every map or in none")
    if sigma is None and maps[0].cov is None:
        raise ValueError("--sigma is needed when the maps give no covariances (sxx, sxy, syy or sigma columns)")
    if sigma is None:
        sigma = pooled_sigma(np.concatenate([m.cov for m in maps[:-1]]), maps[-1].cov)
    return maps, sigma


def warn(message: str) -> None:
    print(f"warning: {message}", file=sys.stderr)


def main(argv=None) -> int:
    """Run the command; returns its exit status (``EXIT_*``). Argument errors exit 2 through argparse."""
    parser = _parser()
    args = parser.parse_args(argv)
    if len(args.maps) < 2:
        parser.error("merge needs at least two map files")
    try:
        return _merge(args) if len(args.maps) == 2 else _merge_many(args)
    except MemoryError:
        print("mapmerge: error: out of memory; this is a bug (its cost should be bounded by the landmark "
              "counts): please report it with the command and the map files", file=sys.stderr)
    except Exception as exc:  # noqa: BLE001 -- whatever it is, one line and a status of its own
        first = (str(exc).splitlines() or [""])[0]
        print(f"mapmerge: internal error ({type(exc).__name__}: {first}); this is a bug: please report it "
              "with the command and the map files", file=sys.stderr)
    return EXIT_BUG


def _inputs(args, names: list[str]):
    """The checked outputs, the maps read, σ, and the scale check's record and warning (or None);
    ``--strict`` makes the warning a refusal. Raises ``MapFileError``/``ValueError`` on bad input."""
    check_outputs(args)
    maps, sigma = read_maps(args.maps, args.sigma)
    scale, mismatch = scale_check(maps, names)
    if mismatch and args.strict:
        raise ValueError(f"{mismatch} (refused: --strict)")
    if mismatch:
        warn(mismatch)
    return maps, sigma, scale, mismatch


def _frame(theta_deg: float, theta_std_deg: float, t, t_std) -> str:
    return (f"theta = {with_std(theta_deg, theta_std_deg)} deg, "
            f"t = ({with_std(t[0], t_std[0])}, {with_std(t[1], t_std[1])})")


def _merge(args) -> int:
    try:
        (map_p, map_q), sigma, scale, mismatch = _inputs(args, ["map a", "map b"])
        res = merge_maps(map_p.points, map_q.points, sigma, tau=args.tau, method=args.method,
                         cov_p=map_p.cov, cov_q=map_q.cov, rng=args.seed)
    except (MapFileError, ValueError, ImportError) as exc:
        print(f"mapmerge: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    info = {**summary(res), "sigma": float(sigma), "scale": scale, "units": JSON_UNITS}
    info["warnings"] = [mismatch] if mismatch else []
    if not res.matched:
        info["output"] = None
        print(json.dumps(info) if args.json else
              f"no match: {args.maps[1]} could not be matched to {args.maps[0]} (method {res.method}); "
              "nothing written", file=sys.stdout if args.json else sys.stderr)
        return EXIT_NO_MATCH
    info["second_match"], info["rigid_check"], warnings = _checks_of_the_match(map_p, map_q, res, sigma, args.tau)
    info["warnings"] += warnings
    try:
        info["output"] = str(write_map(res, args.output, map_p, map_q))
        if args.plot:
            from .plotting import plot_merge

            info["plot"] = str(plot_merge(res, map_p.points, map_q.points, args.plot))
    except OSError as exc:  # e.g. no permission to write
        print(f"mapmerge: error: cannot write {exc.filename or args.output}: {exc.strerror or exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    if args.json:
        print(json.dumps(info))
    else:
        _print_merge(info, res, args)
    for message in warnings:
        warn(message)
    return EXIT_MATCHED


def _checks_of_the_match(map_p: LandmarkMap, map_q: LandmarkMap, res, sigma: float, tau):
    """A second rigid match among the unpaired landmarks and the rigid check of the pairs: their
    ``--json`` entries and the warnings they call for."""
    second = residual_match(map_p.points, map_q.points, res, sigma, tau, map_p.cov, map_q.cov)
    second_info = ({"pairs": int(len(second.pairs)), "rotation_offset_deg": float(np.degrees(second.rotation_offset))}
                   if second.matched else None)
    rigid = rigid_check(map_p.points, map_q.points, res, sigma, map_p.cov, map_q.cov)
    rigid_info = {"agree": rigid.agree, "outliers": rigid.n_outliers, "bound": rigid.bound,
                  "max_stat": rigid.max_stat, "wrong_merge": rigid.n_outliers > WRONG_MERGE_SHARE * len(res.pairs)}
    warnings = []
    if second.matched:
        warnings.append(f"the landmarks left unpaired hold a second rigid match ({len(second.pairs)} pairs, "
                        f"rotated {np.degrees(second.rotation_offset):.2f} deg against the first): one map is "
                        "bent, so the combined map aligns only the larger matched part and holds the other "
                        "part's common landmarks twice" + ("" if res.method in ("consensus", "consensus_count") else
                                                           f", or the {res.method} match is wrong"))
    if res.method in UNTESTED_METHODS and not rigid.agree:
        wrong = rigid_info["wrong_merge"]
        warnings.append((f"the {res.method} merge is probably wrong: {rigid.n_outliers} of its" if wrong else
                         f"{rigid.n_outliers} of the {res.method} merge's")
                        + f" {len(res.pairs)} landmark pairs lie off its rigid motion, "
                        f"beyond the chi-square bound (largest {rigid.max_stat:.3g} against {rigid.bound:.3g})"
                        + (f", and {res.n_conflicts} were dropped as conflicts" if res.n_conflicts else "")
                        + ("" if wrong else ": those pairs are probably wrong, their fused rows join two "
                           "landmarks") + f"; {res.method} has no acceptance test (consensus has)")
    return second_info, rigid_info, warnings


def _print_merge(info: dict, res, args) -> None:
    """The text report of a matched pair of maps (``--json`` prints ``info`` instead)."""
    frame = _frame(info["theta_deg"], info["theta_std_deg"], info["t"], info["t_std"])
    print(f"matched ({res.method}): {frame} [q ≈ R(theta) p + t]; {info['pairs']} landmark pairs, "
          f"{info['conflicts']} "
          f"conflict{'' if info['conflicts'] == 1 else 's'}")
    if args.sigma is None:
        print(f"sigma = {info['sigma']:.6g} (RMS of the maps' own standard deviations)")
    print(f"combined map: {len(res.merged)} landmarks -> {info['output']}"
          + (f"; plot -> {info['plot']}" if args.plot else ""))


def _merge_many(args) -> int:
    """Three or more maps: ``merge_many``, the fused map written, one line per map."""
    try:
        maps, sigma, scale, mismatch = _inputs(args, args.maps)
        covs = None if maps[0].cov is None else [m.cov for m in maps]
        group = merge_many([m.points for m in maps], None if covs is not None and args.sigma is None else sigma,
                           covs, method=args.method, tau=args.tau, rng=args.seed)
    except (MapFileError, ValueError, ImportError) as exc:
        print(f"mapmerge: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    warnings = [f"{args.maps[e.i]} and {args.maps[e.j]} matched, but their motion disagrees with the others' "
                 "around a cycle: that match was not used" for e in group.edges if e.status == INCONSISTENT]
    warnings += [f"{path} matched no other map: left out of the fused map"
                 for path, placed in zip(args.maps, group.placed) if not placed]
    info = {"matched": group.n_placed >= 2, "method": args.method, "sigma": float(sigma), "scale": scale,
            "reference": args.maps[group.reference], "edges": group.edge_counts(), "maps": [],
            "landmarks": int(len(group.merged)), "units": JSON_UNITS,
            "warnings": ([mismatch] if mismatch else []) + warnings}
    for k, path in enumerate(args.maps):
        std = np.sqrt(np.diag(group.frame_cov[k]))
        info["maps"].append({"file": path, "placed": bool(group.placed[k]), "theta": float(group.theta[k]),
                             "theta_std": float(std[0]), "theta_deg": float(np.degrees(group.theta[k])),
                             "theta_std_deg": float(np.degrees(std[0])), "t": [float(v) for v in group.t[k]],
                             "t_std": [float(v) for v in std[1:]],
                             "landmarks_shared": int(((group.tracks[:, k] >= 0)
                                                      & ((group.tracks >= 0).sum(axis=1) >= 2)).sum())})
    if not info["matched"]:
        info["output"] = None
        print(json.dumps(_finite(info)) if args.json else
              f"no match: none of the {len(args.maps)} maps could be matched to another (method {args.method}); "
              "nothing written", file=sys.stdout if args.json else sys.stderr)
        return EXIT_NO_MATCH
    try:
        info["output"] = str(write_group(group, args.output, maps))
        if args.plot:
            from .plotting import plot_group

            info["plot"] = str(plot_group(group, [m.points for m in maps], args.plot, args.maps))
    except OSError as exc:
        print(f"mapmerge: error: cannot write {exc.filename or args.output}: {exc.strerror or exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    if args.json:
        print(json.dumps(_finite(info)))
    else:
        print(f"merged {group.n_placed} of {len(maps)} maps ({args.method}) in {info['reference']}'s frame "
              f"[map ≈ R(theta) x + t]; {info['edges']['accepted']} pairwise matches used")
        for m in info["maps"]:
            if m["placed"]:
                print(f"  {m['file']}: {_frame(m['theta_deg'], m['theta_std_deg'], m['t'], m['t_std'])}; "
                      f"{m['landmarks_shared']} landmarks shared with other maps")
            else:
                print(f"  {m['file']}: not placed")
        print(f"fused map: {len(group.merged)} landmarks -> {info['output']}"
              + (f"; plot -> {info['plot']}" if args.plot else ""))
    for message in warnings:
        warn(message)
    return EXIT_MATCHED


def _finite(value):
    """``value`` with NaN (an unplaced map's frame) as None, so that ``--json`` prints valid JSON."""
    if isinstance(value, float):
        return None if math.isnan(value) else value
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_finite(v) for v in value]
    return value


if __name__ == "__main__":
    sys.exit(main())

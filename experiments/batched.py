"""Batched Monte Carlo trials of the paper's matchers: a chunk per numpy call.

A Fig. 3 trial is tiny (10-20 landmarks, 10-35 triangles), so the per-trial
path (``trials.run_trial``) spends its time in Python and in the fixed cost
of a hundred small numpy calls, not in arithmetic. Here a whole chunk of
trials runs stage by stage. Per trial only what cannot be shared: its own
random stream, its three Delaunay triangulations (truth, map p, map q) and
its assignment LP. Everything else -- σ from the SNR, the noisy maps, Groth
order, the GLRT of every triangle pair, labels, correspondences, the
n-point alignment, the combined map and its errors -- is a few numpy calls
over all trials of the chunk.

The draws are those of ``mapmerge.simulate.make_pair`` (same streams, same
order), and the statistics are those of ``merge_maps`` for
``method="paper"``/``"cyclic"``; the results equal the per-trial path's up
to floating-point rounding (tested). Every value depends on its own trial
only: arithmetic over padded triangle arrays is elementwise and per-trial
sums run in a fixed, trial-local order, so results are bit-identical for
any chunking, worker count or resume (tested).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, fields, replace

import numpy as np
import pandas as pd
from scipy.optimize import linear_sum_assignment
from scipy.spatial import Delaunay

from mapmerge.matching import lp_weight, resolve_correspondences, resolve_log_tau
from mapmerge.merging import MIN_MATCHED_LANDMARKS
from mapmerge.simulate import _check_scenario, rotate, sigmas_from_snr
from mapmerge.statistic import _min_cost, ccw_order, wrap_angle
from mapmerge.triangles import groth_order

#: Matcher methods the batched engine runs (the LP methods without a
#: verification step); the others go through ``trials.run_trial``.
BATCHED_METHODS = ("paper", "cyclic")


def supports(scenario: dict, matcher: dict) -> bool:
    """Whether a cell can run batched: synthetic maps, a paper-style matcher."""
    return scenario.get("kind", "synthetic") == "synthetic" and matcher["method"] in BATCHED_METHODS


#: Triangle pairs held at once (about 32 MB per array of scores): a chunk
#: of big maps runs in slices of trials that fit.
MAX_PAIRS = 2**22


def run_chunk(root_seed: int, scenario: dict, matcher: dict, start: int, stop: int):
    """Trials ``start..stop-1`` of a cell as (trials, pairs) DataFrames.

    Same rows and columns as ``trials.run_chunk`` on the per-trial path.
    The timing columns hold the time per trial of the slice of trials run
    together (matching: the two maps' triangulation, scoring and LP;
    merging: per τ rule).
    """
    n, c = _check_scenario(scenario["n_landmarks"], scenario["overlap"], scenario["snr_db"],
                           scenario["aspect"])
    # At most 2n - 5 triangles per map; trials are independent, so slicing
    # changes nothing but memory.
    per_slice = max(1, MAX_PAIRS // max(2 * n - 5, 1) ** 2)
    parts = [_run_slice(root_seed, scenario, matcher, a, min(a + per_slice, stop), n, c)
             for a in range(start, stop, per_slice)]
    if len(parts) == 1:
        return parts[0]
    return tuple(pd.concat([p[k] for p in parts], ignore_index=True) for k in (0, 1))


def _run_slice(root_seed: int, scenario: dict, matcher: dict, start: int, stop: int, n: int, c: int):
    from .trials import trial_seeds

    unrelated = bool(scenario["unrelated"])
    trials = np.arange(start, stop)
    B = trials.size
    draws = _draw(n, c, unrelated, trial_seeds(root_seed, scenario, trials))
    height = np.sqrt(n / float(scenario["aspect"]))
    width = float(scenario["aspect"]) * height
    world = _truth(n, c, width, height, unrelated, draws["u"])
    # σ comes from the related world, also for unrelated pairs (make_pair).
    sigma, _ = sigmas_from_snr(world[:, : 2 * n - c], float(scenario["snr_db"]))
    P, Q, ids_p, ids_q, truth_theta, truth_t = _maps(n, c, width, unrelated, draws, world, sigma)
    maps = _Maps.build(P, Q, ids_p, ids_q, truth_theta, truth_t, sigma, world, 0 if unrelated else c)

    clock = time.perf_counter()
    tri_p, tri_q = _Triangles(P), _Triangles(Q)
    cyclic = matcher["method"] == "cyclic"
    vp, vq = tri_p.stat_vertices(cyclic), tri_q.stat_vertices(cyclic)
    log_lr, shift = _pairwise_log_lr(P, Q, vp, vq, tri_p.count, tri_q.count, sigma, cyclic)
    tb, i, j = _assign(log_lr, tri_p.count, tri_q.count, matcher["objective"])
    score, shift = log_lr[tb, i, j], shift[tb, i, j]
    roll = (np.arange(3)[None, :] + shift[:, None].astype(np.intp)) % 3
    pv, qv = vp[tb, i], np.take_along_axis(vq[tb, j], roll, axis=1)
    time_match = (time.perf_counter() - clock) / B

    a = ids_p[tb[:, None], tri_p.vertices[tb, i]]
    b = ids_q[tb[:, None], tri_q.vertices[tb, j]]
    is_true = np.all(np.sort(a, axis=1) == np.sort(b, axis=1), axis=1)
    consistent = np.all(a == b, axis=1)
    n_common = _common_triangles(ids_p, ids_q, tri_p, tri_q, 2 * n)

    columns, last = [], None
    for rule in matcher["taus"]:
        clock = time.perf_counter()
        if rule == "oracle":
            log_tau = _oracle(tb, is_true, score, B)
        else:
            log_tau = np.full(B, resolve_log_tau(rule))
        declared = score >= log_tau[tb]
        row = _counts(tb, is_true, consistent, declared, n_common, B)
        if last is None:
            merged = _merge_errors(maps, tb[declared], pv[declared], qv[declared], score[declared])
        else:  # only trials whose declared set differs from the previous rule's
            merged = _merge_changed(maps, tb, pv, qv, score, declared, *last)
        last = declared, merged
        row = {"trial": trials, "tau": np.full(B, rule, dtype=object), "log_tau": log_tau,
               "sigma": sigma, "n_p": np.full(B, n), "n_q": np.full(B, n),
               "n_common_landmarks": np.full(B, maps.n_common), **row, **merged}
        row["time_merge_s"] = np.full(B, (time.perf_counter() - clock) / B)
        row["time_match_s"] = np.full(B, time_match)
        columns.append(row)
    # Trial-major, rule-minor rows, as the per-trial path writes them.
    trials_df = pd.DataFrame({key: _interleave([col[key] for col in columns]) for key in _ROW_ORDER})
    pairs_df = pd.DataFrame({"trial": trials[tb], "score": score, "label": is_true,
                             "order_consistent": consistent})
    return trials_df, pairs_df


_ROW_ORDER = ("trial", "tau", "log_tau", "sigma", "n_p", "n_q", "n_common_landmarks", "tp", "fp",
              "md", "tn", "common", "unpaired", "order_flips", "matched", "n_pairs", "correct_pairs",
              "wrong_pairs", "missed_pairs", "n_conflicts", "rot_err_deg", "trans_err", "rmse",
              "duplicates", "success", "false_merge", "time_match_s", "time_merge_s")


def _interleave(parts: list[np.ndarray]) -> np.ndarray:
    return np.stack(parts, axis=1).ravel()


def _draw(n: int, c: int, unrelated: bool, seeds) -> dict:
    """Every trial's raw random numbers, consumed exactly as make_pair does.

    make_pair draws its uniforms block by block (x then y of the common
    strip, p's own part, q's own part[, q's unrelated strip]), then two
    permutations, θ, t, and two (n, 2) normal blocks. One ``random`` call
    per run of uniforms consumes the same stream (``uniform(a, b)`` is
    ``a + (b - a)·u``), and ``normal(0, σ)`` is ``0 + σ·standard_normal``.
    """
    B = len(seeds)
    out = {"u": np.empty((B, 2 * c + 4 * (n - c) + (2 * c if unrelated else 0))),
           "perm_p": np.empty((B, n), np.intp), "perm_q": np.empty((B, n), np.intp),
           "u3": np.empty((B, 3)), "z": np.empty((B, 4 * n))}
    for k, seed in enumerate(seeds):
        rng = np.random.default_rng(seed)
        rng.random(out=out["u"][k])
        out["perm_p"][k] = rng.permutation(n)
        out["perm_q"][k] = rng.permutation(n)
        rng.random(out=out["u3"][k])
        rng.standard_normal(out=out["z"][k])
    return out


def _truth(n: int, c: int, width: float, height: float, unrelated: bool, u: np.ndarray) -> np.ndarray:
    """True landmarks (B, L, 2) laid out as make_pair does: row = landmark id."""
    shift = width - width * c / n
    blocks = [(c, shift, width), (n - c, 0.0, shift), (n - c, width, width + shift)]
    if unrelated:
        blocks.append((c, shift, width))
    lo, span, col_x, col_y, at = [], [], [], [], 0
    for k, x0, x1 in blocks:  # k uniforms for x in [x0, x1], then k for y in [0, height]
        lo += [x0] * k + [0.0] * k
        span += [x1 - x0] * k + [height - 0.0] * k
        col_x += range(at, at + k)
        col_y += range(at + k, at + 2 * k)
        at += 2 * k
    values = np.asarray(lo) + np.asarray(span) * u
    return np.stack([values[:, col_x], values[:, col_y]], axis=2)


def _maps(n, c, width, unrelated, draws, world, sigma):
    """Noisy maps p and q (B, n, 2), their row ids and the true (θ, t)."""
    B = len(sigma)
    ids_p = draws["perm_p"]  # p's ids are 0..n-1 before shuffling
    base_q = np.concatenate([(2 * n - c if unrelated else 0) + np.arange(c), n + np.arange(n - c)])
    ids_q = base_q[draws["perm_q"]]
    rows = np.arange(B)[:, None]
    z = sigma[:, None, None, None] * draws["z"].reshape(B, 2, n, 2)
    theta = -np.pi + (np.pi - -np.pi) * draws["u3"][:, 0]
    t = -width + (width - -width) * draws["u3"][:, 1:]
    Q = rotate(theta, world[rows, ids_q]) + t[:, None, :] + z[:, 1]
    return world[rows, ids_p] + z[:, 0], Q, ids_p, ids_q, theta, t


class _Triangles:
    """Delaunay triangles of B maps in Groth order, padded to the most any map has.

    ``vertices`` (B, T, 3) are landmark indices (padding rows point at
    landmark 0 and are never read: ``count`` gives each map's triangles,
    which come first).
    """

    def __init__(self, maps: np.ndarray):
        B = len(maps)
        simplices = [Delaunay(pts).simplices for pts in maps]
        self.count = np.array([len(s) for s in simplices])
        self.trial = np.repeat(np.arange(B), self.count)
        flat = np.concatenate(simplices)
        coords = maps.reshape(-1, 2)[self.trial[:, None] * maps.shape[1] + flat]
        perm = groth_order(coords)
        self.flat = np.take_along_axis(flat, perm, axis=1)
        self._maps = maps
        self.slot = np.arange(len(flat)) - np.repeat(np.cumsum(self.count) - self.count, self.count)
        self.vertices = self._pad(self.flat, B, int(self.count.max()))

    def _pad(self, flat, B, size):
        out = np.zeros((B, size, 3), dtype=np.intp)
        out[self.trial, self.slot] = flat
        return out

    def stat_vertices(self, cyclic: bool) -> np.ndarray:
        """Vertex order of the statistic: Groth, or counter-clockwise for ``cyclic``."""
        if not cyclic:
            return self.vertices
        coords = self._maps.reshape(-1, 2)[self.trial[:, None] * self._maps.shape[1] + self.flat]
        ccw = np.take_along_axis(self.flat, ccw_order(coords), axis=1)
        return self._pad(ccw, *self.vertices.shape[:2])


#: Triangle pairs scored per numpy call: small enough that the temporaries
#: stay in cache (64 trials of 20 landmarks; one trial of a big map).
BLOCK_PAIRS = 2**16


def _pairwise_log_lr(P, Q, vp, vq, count_p, count_q, sigma, cyclic):
    """log Λ (B, T, T) of every triangle pair of every trial.

    Trials go in blocks of about ``BLOCK_PAIRS`` pairs, grouped by triangle
    count so that each block is padded only to its own largest map; values
    are elementwise, so neither can change them. Entries beyond a trial's
    own triangles are left unset.
    """
    block = max(1, BLOCK_PAIRS // (vp.shape[1] * vq.shape[1]))
    # 2σ² as merge_maps computes it from a Python float (pow, not x·x), so
    # that scores equal the per-trial path's to the bit.
    two_var = 2.0 * np.array([s**2 for s in sigma.tolist()])
    flat_p, flat_q = P.reshape(-1, 2), Q.reshape(-1, 2)
    log_lr = np.empty((len(P), vp.shape[1], vq.shape[1]))
    shift = np.empty(log_lr.shape, dtype=np.int8)
    order = np.lexsort((count_q, count_p))
    for a in range(0, len(P), block):
        trials = order[a:a + block]
        tp, tq = count_p[trials].max(), count_q[trials].max()
        rows = trials[:, None, None] * P.shape[1]
        cost, s = _min_cost(flat_p[rows + vp[trials, :tp]], flat_q[rows + vq[trials, :tq]], cyclic, pairwise=True)
        log_lr[trials, :tp, :tq] = cost / -two_var[trials, None, None]  # = -cost / 2σ², bit for bit
        shift[trials, :tp, :tq] = s
    return log_lr, shift


def _assign(log_lr, count_p, count_q, objective):
    """The LP (14) of every trial on its own triangles: (trial, i, j) of all tentative pairs."""
    weight = lp_weight(log_lr, objective)
    parts = [linear_sum_assignment(weight[k, : count_p[k], : count_q[k]], maximize=True)
             for k in range(len(weight))]
    tb = np.repeat(np.arange(len(parts)), [len(i) for i, _ in parts])
    return tb, np.concatenate([i for i, _ in parts]), np.concatenate([j for _, j in parts])


def _common_triangles(ids_p, ids_q, tri_p, tri_q, n_ids: int) -> np.ndarray:
    """Per trial, the triangles with the same landmark-id set in both maps."""
    def keys(ids, tri):
        s = np.sort(ids[tri.trial[:, None], tri.flat], axis=1).astype(np.int64)
        return ((tri.trial * n_ids + s[:, 0]) * n_ids + s[:, 1]) * n_ids + s[:, 2]

    both = np.intersect1d(keys(ids_p, tri_p), keys(ids_q, tri_q), assume_unique=True)
    return np.bincount(both // n_ids**3, minlength=len(ids_p))


def _oracle(tb, is_true, score, B) -> np.ndarray:
    """Per trial, the smallest log τ with zero false positives (metrics.oracle_log_tau)."""
    best_false = np.full(B, -np.inf)
    np.maximum.at(best_false, tb[~is_true], score[~is_true])
    return np.where(np.isneginf(best_false), -np.inf, np.nextafter(best_false, np.inf))


def _counts(tb, is_true, consistent, declared, n_common, B) -> dict:
    def per_trial(mask):
        return np.bincount(tb[mask], minlength=B)

    tp, md = per_trial(is_true & declared), per_trial(is_true & ~declared)
    return {"tp": tp, "fp": per_trial(~is_true & declared), "md": md,
            "tn": per_trial(~is_true & ~declared), "common": n_common,
            "unpaired": n_common - tp - md, "order_flips": per_trial(is_true & ~consistent)}


@dataclass(frozen=True)
class _Maps:
    """B trials' maps and ground truth, with what every τ rule's evaluation shares."""

    P: np.ndarray
    Q: np.ndarray
    ids_p: np.ndarray
    ids_q: np.ndarray
    theta: np.ndarray
    t: np.ndarray
    sigma: np.ndarray
    at_p: np.ndarray  # true position of each row of P / of Q (in p's frame)
    at_q: np.ndarray
    err_p: np.ndarray  # squared error of each row of P
    n_common: int  # common landmarks per trial

    @classmethod
    def build(cls, P, Q, ids_p, ids_q, theta, t, sigma, world, n_common):
        rows = np.arange(len(world))[:, None]
        at_p = world[rows, ids_p]
        return cls(P, Q, ids_p, ids_q, theta, t, sigma, at_p, world[rows, ids_q],
                   np.sum((P - at_p) ** 2, axis=2), n_common)

    def take(self, trials: np.ndarray) -> "_Maps":
        return replace(self, **{f.name: getattr(self, f.name)[trials] for f in fields(self)
                                if f.name != "n_common"})


def _merge_changed(maps: _Maps, tb, pv, qv, score, declared, last_declared, last_merged) -> dict:
    """``_merge_errors`` of the trials whose declared pairs changed; the rest copied."""
    changed = np.bincount(tb[declared != last_declared], minlength=len(maps.P)) > 0
    merged = {key: value.copy() for key, value in last_merged.items()}
    sub = np.flatnonzero(changed)
    if sub.size:
        keep = declared & changed[tb]
        renumber = np.cumsum(changed) - 1
        part = _merge_errors(maps.take(sub), renumber[tb[keep]], pv[keep], qv[keep], score[keep])
        for key, value in part.items():
            merged[key][sub] = value
    return merged


def _merge_errors(maps: _Maps, tb, pv, qv, score) -> dict:
    """Correspondences, n-point alignment and combined-map errors of every trial.

    The batched ``merge_at`` + ``metrics.map_errors``: landmark indices are
    offset by ``trial·n`` so one call resolves every trial's conflicts.
    """
    P, Q = maps.P, maps.Q
    B, n = P.shape[:2]
    uniq, keep = resolve_correspondences(tb[:, None] * n + pv, tb[:, None] * n + qv, score)
    n_conflicts = np.bincount(uniq[~keep, 0] // n, minlength=B)
    pairs = uniq[keep]
    kt, pi, qi = pairs[:, 0] // n, pairs[:, 0] % n, pairs[:, 1] % n
    K = np.bincount(kt, minlength=B)
    matched = K >= MIN_MATCHED_LANDMARKS
    correct = np.bincount(kt, maps.ids_p[kt, pi] == maps.ids_q[kt, qi], B).astype(np.int64)

    # n-point closed form (statistic.paired_transforms) with per-trial sums.
    Pk, Qk = P[kt, pi], Q[kt, qi]
    with np.errstate(invalid="ignore", divide="ignore"):
        p_bar = np.stack([np.bincount(kt, Pk[:, d], B) for d in (0, 1)], axis=1) / K[:, None]
        q_bar = np.stack([np.bincount(kt, Qk[:, d], B) for d in (0, 1)], axis=1) / K[:, None]
    px, py = (Pk - p_bar[kt]).T
    qx, qy = (Qk - q_bar[kt]).T
    alpha = -np.bincount(kt, qx * px + qy * py, B)
    beta = -np.bincount(kt, px * qy - py * qx, B)
    theta = np.where(matched, wrap_angle(np.arctan2(-beta, -alpha)), np.nan)
    t = q_bar - rotate(theta, p_bar[:, None, :])[:, 0]

    # Combined map (15): fused pairs, p-only rows, q-only rows mapped into p.
    mapped = rotate(-theta, Q - t[:, None, :])
    err_q = np.sum((mapped - maps.at_q) ** 2, axis=2)
    mu = 0.5 * (Pk + mapped[kt, qi])
    err_fused = np.bincount(kt, np.sum((mu - maps.at_p[kt, pi]) ** 2, axis=1), B)
    paired_p = np.zeros((B, n), bool)
    paired_q = np.zeros((B, n), bool)
    paired_p[kt, pi] = True
    paired_q[kt, qi] = True
    sq_err = err_fused + np.where(paired_p, 0.0, maps.err_p).sum(axis=1) + np.where(paired_q, 0.0, err_q).sum(axis=1)
    rmse = np.sqrt(sq_err / (2 * n - K))
    rot_err_deg = np.degrees(np.abs(wrap_angle(theta - maps.theta)))
    trans_err = np.sqrt(np.sum((t - maps.t) ** 2, axis=1))
    # q-only rows of landmarks p holds too (p's ids are 0..n-1).
    duplicates = np.sum(~paired_q & (maps.ids_q < n), axis=1)
    nan = np.where(matched, 0.0, np.nan)
    return {
        "matched": matched, "n_pairs": K, "correct_pairs": correct, "wrong_pairs": K - correct,
        "missed_pairs": maps.n_common - correct, "n_conflicts": n_conflicts,
        "rot_err_deg": rot_err_deg + nan, "trans_err": trans_err + nan, "rmse": rmse + nan,
        "duplicates": np.where(matched, duplicates, 0),
        "success": matched & (rot_err_deg < 1.0) & (rmse < 2.0 * maps.sigma),
        "false_merge": matched & (maps.n_common == 0),
    }

"""Geometry of example trials, as tables, for the paper's Fig. 1 and Fig. 2.

A trial is recomputed from its seed, so examples need no state from the
Monte Carlo run. The first τ rule of the matcher is used.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from mapmerge import metrics
from mapmerge.merging import get_method, match_stage, merge_at

from .trials import make_trials, matcher_covariances, pair_labels, rule_log_tau


def _triangle_status(n_tri, side, triangle_pairs, is_true, declared, common):
    """Status of every triangle of one map: tp, fp, md, tn, unpaired or other."""
    status = np.full(n_tri, "other", dtype=object)
    status[common[:, side]] = "unpaired"  # overwritten below when LP paired it right
    label = np.where(is_true, np.where(declared, "tp", "md"), np.where(declared, "fp", "tn"))
    # A common triangle the LP paired with a wrong partner stays "unpaired"
    # unless that wrong pairing was declared (then it is a false positive).
    idx = triangle_pairs[:, side]
    keep = is_true | declared | (status[idx] != "unpaired")
    # A triangle in several pairs (consensus keeps the LP's undeclared ones)
    # shows its most telling status: tp over fp over md over tn.
    rank = np.select([label == "tp", label == "fp", label == "md"], [3, 2, 1], 0)
    order = np.flatnonzero(keep)[np.argsort(rank[keep], kind="stable")]
    status[idx[order]] = label[order]
    return status


def example_tables(seed: int, scenario: dict, matcher: dict, trials) -> dict[str, pd.DataFrame]:
    """Triangles with their detection status, landmarks and the combined map.

    Returns
    -------
    dict
        ``example_triangles``: one row per triangle of either map (its own
        frame), with status; ``example_landmarks``: rows of kind ``p``, ``q``
        (own frames), ``merged`` (p's frame, with origin) and ``truth``.
    """
    tri_rows, lm_rows = [], []
    batch, _ = make_trials(seed, scenario, list(trials))
    method = get_method(matcher["method"])
    rule = matcher["taus"][0] if method.uses_tau else "none"
    match = match_stage(batch.p, batch.q, batch.sigma, method.name, matcher.get("objective", "lr"))
    lp_true = None if match is None else pair_labels(batch, match.tri_p, match.tri_q, match.trial,
                                                     match.triangle_pairs)[0]
    merged = merge_at(batch.p, batch.q, batch.sigma, match, rule_log_tau(rule, match, lp_true, len(batch)),
                      method=method.name, **matcher_covariances(batch, matcher))
    for b, k in enumerate(trials):
        sc, res = batch[b], merged.result(b)
        vp, vq = res.tri_p.vertices, res.tri_q.vertices
        is_true, _ = metrics.triangle_labels(sc.ids_p, sc.ids_q, vp, vq, res.triangle_pairs)
        common = metrics.common_triangles(sc.ids_p, sc.ids_q, vp, vq)
        for side, (name, tri) in enumerate((("p", res.tri_p), ("q", res.tri_q))):
            status = _triangle_status(len(tri), side, res.triangle_pairs, is_true, res.declared, common)
            xy = tri.coords.reshape(len(tri), 6)
            tri_rows.append(pd.DataFrame({
                "trial": k, "map": name, "tau": rule, "status": status,
                **{f"{c}{v}": xy[:, 2 * (v - 1) + (c == "y")] for v in (1, 2, 3) for c in "xy"},
            }))
        c = res.combined
        merged_ids = np.where(c.index_p >= 0, sc.ids_p[c.index_p], sc.ids_q[c.index_q])
        n_p, n_q, n_t = len(sc.p), len(sc.q), len(sc.truth)
        for kind, pts, ids, origin, index_p, index_q in (
            ("p", sc.p, sc.ids_p, "p", np.arange(n_p), np.full(n_p, -1)),
            ("q", sc.q, sc.ids_q, "q", np.full(n_q, -1), np.arange(n_q)),
            ("merged", c.points, merged_ids, c.origin, c.index_p, c.index_q),
            ("truth", sc.truth, np.arange(n_t), "truth", np.full(n_t, -1), np.full(n_t, -1)),
        ):
            lm_rows.append(pd.DataFrame({
                "trial": k, "kind": kind, "x": pts[:, 0], "y": pts[:, 1], "id": ids,
                "origin": origin, "sigma": sc.sigma, "tau": rule, "index_p": index_p, "index_q": index_q,
            }))
    return {
        "example_triangles": pd.concat(tri_rows, ignore_index=True),
        "example_landmarks": pd.concat(lm_rows, ignore_index=True),
    }

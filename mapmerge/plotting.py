"""Pictures of a merge (needs matplotlib): two maps in p's frame, fused pairs linked; or every map of a team."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .alignment import rotate
from .result import MergeResult


def plot_merge(res: MergeResult, P: np.ndarray, Q: np.ndarray, path) -> Path:
    """Draw map p, map q brought into p's frame, the fused pairs linked, the unmatched marked.

    Parameters
    ----------
    res : MergeResult
        A match (``res.matched``).
    P, Q : (n, 2) ndarray
        The two maps as merged.
    path : path
        Image file (PNG, PDF, ...).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection

    q_in_p = rotate(-res.theta, Q - res.t)
    paired_p = np.zeros(len(P), bool)
    paired_q = np.zeros(len(Q), bool)
    paired_p[res.pairs[:, 0]] = True
    paired_q[res.pairs[:, 1]] = True
    fig, ax = plt.subplots(figsize=(5.0, 4.4))
    ax.add_collection(LineCollection(np.stack([P[res.pairs[:, 0]], q_in_p[res.pairs[:, 1]]], axis=1),
                                     colors="0.3", lw=0.8, label=f"fused pairs ({len(res.pairs)})"))
    ax.scatter(*P[paired_p].T, s=14, c="tab:blue", label="map p, paired")
    ax.scatter(*q_in_p[paired_q].T, s=14, marker="x", c="tab:orange", lw=0.9, label="map q, paired")
    ax.scatter(*P[~paired_p].T, s=22, facecolors="none", edgecolors="tab:blue",
               label=f"map p only ({int((~paired_p).sum())})")
    ax.scatter(*q_in_p[~paired_q].T, s=22, marker="s", facecolors="none", edgecolors="tab:orange",
               label=f"map q only ({int((~paired_q).sum())})")
    ax.set_aspect("equal")
    ax.set_xlabel("x in map p's frame")
    ax.set_ylabel("y in map p's frame")
    ax.set_title(f"{res.method}: θ = {np.degrees(res.theta):.3f}°, {len(res.pairs)} pairs", fontsize=9)
    ax.legend(fontsize=7, frameon=False, loc="best")
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, metadata={"Software": None} if path.suffix.lower() == ".png" else None)
    plt.close(fig)
    return path


def plot_group(group, maps, path, names=None) -> Path:
    """Draw every placed map of a ``merge_many`` result in the reference frame, one colour per map.

    Parameters
    ----------
    group : GroupMerge
    maps : sequence of (n_i, 2) ndarray
        The maps as merged.
    path : path
        Image file (PNG, PDF, ...).
    names : sequence of str, optional
        Legend labels (default ``map 0``, ``map 1``, ...).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [f"map {k}" for k in range(len(maps))] if names is None else list(names)
    fig, ax = plt.subplots(figsize=(5.6, 4.6))
    markers = ["o", "x", "s", "+", "^", "D", "v", "*", "<", ">"]
    for k in np.flatnonzero(group.placed):
        x = rotate(-group.theta[k], np.asarray(maps[k], dtype=float) - group.t[k])
        ax.scatter(*x.T, s=14, marker=markers[k % len(markers)], lw=0.8, label=f"{names[k]} ({len(x)})")
    shared = (group.tracks >= 0).sum(axis=1) >= 2
    ax.scatter(*group.merged[shared].T, s=40, facecolors="none", edgecolors="0.2", lw=0.6,
               label=f"fused, seen by 2+ maps ({int(shared.sum())})")
    ax.set_aspect("equal")
    ax.set_xlabel(f"x in {names[group.reference]}'s frame")
    ax.set_ylabel(f"y in {names[group.reference]}'s frame")
    ax.set_title(f"{group.n_placed} of {len(maps)} maps placed, {len(group.merged)} landmarks", fontsize=9)
    ax.legend(fontsize=7, frameon=False, loc="center left", bbox_to_anchor=(1.02, 0.5))
    path = Path(path)
    # The legend sits outside the axes: the saved box grows to hold it.
    fig.savefig(path, bbox_inches="tight", metadata={"Software": None} if path.suffix.lower() == ".png" else None)
    plt.close(fig)
    return path

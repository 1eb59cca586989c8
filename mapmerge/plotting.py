"""A picture of one merge: both maps in p's frame, fused pairs linked (needs matplotlib)."""

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

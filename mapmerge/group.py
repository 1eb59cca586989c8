"""Merge N agents' landmark maps into one globally consistent map.

``merge_many`` generalises the two-map pipeline to a team of N maps:

1. **Pairwise merges.** Every pair of maps (or, for large teams, each map
   with its ``CANDIDATE_NEIGHBOURS`` most similar maps by a cheap score:
   how many of their landmarks have nearly equal neighbourhoods) is
   merged by ``merge_maps``. A matched pair (i, j) is an *edge*: a rigid
   motion ``map_j ≈ R(θ_ij) map_i + t_ij`` with its (θ, t) covariance and
   its landmark correspondences.
2. **Consistency around cycles.** Edges are taken strongest first (most
   correspondences). An edge joining two groups of maps not yet connected
   extends their spanning tree; an edge inside a group closes a cycle, and
   is kept only when the tree's motion from i to j, composed along the
   tree path with its propagated covariance, agrees with the edge within
   the χ²₃ bound of tail probability ``CYCLE_P``. An edge that fails is
   *inconsistent* and takes no further part. The kept edges are one
   mutually consistent set (every cycle they close passed its test when it
   was closed).
3. **Tracks.** Landmarks linked by the kept edges' correspondences form
   connected components. A component holding two landmarks of one map is
   split: its links are re-added closest first (Mahalanobis distance of the
   two landmarks in the reference frame) and a link that would put two
   landmarks of one map in one track is dropped.
4. **Joint maximum likelihood.** Unknowns: every placed frame (θ_i, t_i)
   but the reference's, and every landmark seen by two or more maps (in the
   reference frame). Each landmark estimate of map i observes
   ``R(θ_i) x + t_i`` with its own covariance. Gauss-Newton from the
   spanning-tree initialisation solves it, eliminating the landmarks by
   their Schur complement (each observation couples one frame and one
   landmark, so the reduced system has only 3 unknowns per map), with Huber
   weights (``HUBER_K``) so that a wrong correspondence cannot drag a frame.
   For two maps and equal noise this is the closed form of the paper's
   eq. (15); frame and landmark covariances are the blocks of the inverse
   Fisher information.

The baselines use the same pairwise merges: ``placement="tree"`` places
every map along the maximum spanning tree of all matched pairs (weight: the
number of correspondences) and ``"chain"`` places the maps in order, map k
through its match with the latest placed map that matched it (sequential
chaining). Neither checks cycles nor optimises jointly: their landmarks are
the information-weighted means of the placed estimates.

A map that joins nobody is unplaced, never forced: the result's frame is
``reference``'s when it is placed, else that of the lowest-numbered map of
the largest group.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.sparse.csgraph import connected_components, minimum_spanning_tree
from scipy.spatial import cKDTree
from scipy.special import chdtri

from ._validation import check_covariances, check_points, check_rng, check_sigma
from .alignment import ROT90, covariance_in_p_frame, mapped_covariance, rotate, rotation, wrap_angle
from .matching import resolve_log_tau
from .merging import DEFAULT_METHOD, DEFAULT_TAU, get_method, merge_maps

#: Tail probability of the χ²₃ test a cycle of edges must pass: a cycle of
#: correct edges is refused this often (with correct covariances).
CYCLE_P = 1e-3
#: Huber threshold on an observation's whitened residual norm in the joint
#: ML: a correct landmark estimate lies beyond it with probability e^(-K²/2) ≈ 1 %.
HUBER_K = 3.0
#: Teams up to this size try every pair of maps (435 merges at 30); larger ones only candidates.
ALL_PAIRS_MAX_AGENTS = 30
#: Candidate partners per map in a large team (by the neighbourhood score of ``candidate_pairs``).
CANDIDATE_NEIGHBOURS = 6
#: Neighbours in a landmark's descriptor, and the descriptors' match gate (in 2σ√k).
DESCRIPTOR_NEIGHBOURS = 10
DESCRIPTOR_GATE = 1.0
#: Gauss-Newton: most iterations, and the step (relative to the maps' extent) that ends them.
GN_MAX_ITER = 50
GN_TOL = 1e-10
#: How the frames are found: see the module docstring.
PLACEMENTS = ("joint", "tree", "chain")
#: An edge's status after assembly.
ACCEPTED, INCONSISTENT, NO_MATCH = "accepted", "inconsistent", "no match"


@dataclass(frozen=True)
class Edge:
    """One pairwise merge of a team: ``maps[j] ≈ R(θ) maps[i] + t``.

    Attributes
    ----------
    i, j : int
        The maps, i < j.
    status : {"accepted", "inconsistent", "no match"}
        Matched and kept; matched but refused by the cycle test; not matched.
    theta : float
        Rotation (NaN when not matched).
    t : (2,) ndarray
    cov : (3, 3) ndarray
        Covariance of (θ, t_x, t_y) (NaN when not matched).
    pairs : (m, 2) int ndarray
        Landmark correspondences (row in map i, row in map j).
    """

    i: int
    j: int
    status: str
    theta: float
    t: np.ndarray
    cov: np.ndarray
    pairs: np.ndarray

    @property
    def matched(self) -> bool:
        return self.status != NO_MATCH


@dataclass(frozen=True)
class GroupMerge:
    """Outcome of ``merge_many``: N maps in the frame of map ``reference``.

    Attributes
    ----------
    reference : int
        The map whose frame the result is in.
    placed : (N,) bool ndarray
        Maps brought into that frame.
    theta, t : (N,), (N, 2) ndarray
        Map i's frame: ``maps[i] ≈ R(θ_i) x + t_i`` for x in the reference
        frame (NaN for unplaced maps; 0 for the reference).
    frame_cov : (N, 3, 3) ndarray
        Covariance of (θ_i, t_i) (zeros for the reference, NaN unplaced).
    tracks : (K, N) int ndarray
        Row of fused landmark k in map i, or -1 (every landmark of a placed
        map is in exactly one track; unplaced maps' columns are all -1).
    merged : (K, 2) ndarray
        The fused landmarks in the reference frame.
    merged_cov : (K, 2, 2) ndarray
    edges : list of Edge
        Every pairwise merge tried.
    placement : str
    """

    reference: int
    placed: np.ndarray
    theta: np.ndarray
    t: np.ndarray
    frame_cov: np.ndarray
    tracks: np.ndarray
    merged: np.ndarray
    merged_cov: np.ndarray
    edges: list
    placement: str

    @property
    def n_placed(self) -> int:
        return int(self.placed.sum())

    def edge_counts(self) -> dict:
        """Number of edges of each status."""
        return {s: sum(e.status == s for e in self.edges) for s in (ACCEPTED, INCONSISTENT, NO_MATCH)}


def merge_many(maps, sigma=None, covs=None, *, method: str = DEFAULT_METHOD, tau=DEFAULT_TAU, reference: int = 0,
               placement: str = "joint", candidates=None, n_jobs: int = 1, rng=None) -> GroupMerge:
    """Merge N landmark maps into one map in the frame of one of them.

    Parameters
    ----------
    maps : sequence of N (n_i, 2) array_like
        Each agent's landmark map in its own frame, N >= 2, each as
        ``merge_maps`` takes a map.
    sigma : float or (N,) array_like, optional
        Per-coordinate standard deviation of each map's landmarks (one for
        all, or one per map). May be left out when ``covs`` are given.
    covs : sequence of N arrays, optional
        Each map's per-landmark covariances, (n_i, 2, 2), or (n_i,)
        variances per coordinate.
    method, tau
        The pairwise method and threshold, as for ``merge_maps``.
    reference : int, default 0
        The map whose frame the result is in, when it is placed.
    placement : {"joint", "tree", "chain"}, default "joint"
        Cycle-checked joint ML (the method), or a baseline (module docstring).
    candidates : None, "all" or int, optional
        Pairs of maps to merge: every pair ("all"), or each map with its
        ``candidates`` most similar maps; default "all" up to
        ``ALL_PAIRS_MAX_AGENTS`` maps, else ``CANDIDATE_NEIGHBOURS``.
    n_jobs : int, default 1
        Processes for the pairwise merges (joblib, the extra ``[parallel]``; -1: every core).
    rng : None, int, SeedSequence or Generator
        Randomness of randomised pairwise methods, one independent stream per
        pair of maps (the same result for any ``n_jobs``).

    Returns
    -------
    GroupMerge

    Raises
    ------
    ValueError
        On fewer than two maps, an invalid map (naming it), ``sigma``,
        ``covs``, ``method``, ``tau``, ``reference``, ``placement``,
        ``candidates`` or ``n_jobs``.
    """
    maps, sigmas, covs = _check_team(maps, sigma, covs)
    get_method(method)
    resolve_log_tau(tau)
    if not (isinstance(reference, (int, np.integer)) and 0 <= reference < len(maps)):
        raise ValueError(f"reference must be a map index in [0, {len(maps) - 1}], got {reference!r}")
    if placement not in PLACEMENTS:
        raise ValueError(f"placement must be one of {PLACEMENTS}, got {placement!r}")
    if not (isinstance(n_jobs, (int, np.integer)) and n_jobs != 0 and n_jobs >= -1):
        raise ValueError(f"n_jobs must be a positive integer or -1, got {n_jobs!r}")
    pairs = candidate_pairs(maps, sigmas, candidates)
    edges = pairwise_edges(maps, sigmas, covs, pairs, method=method, tau=tau, n_jobs=n_jobs, rng=check_rng(rng),
                           sigma_given=sigma is not None)
    variances = [np.broadcast_to(s**2 * np.eye(2), (len(m), 2, 2)) if c is None else c
                 for m, s, c in zip(maps, sigmas, covs)]
    return assemble(maps, variances, edges, int(reference), placement)


def _check_team(maps, sigma, covs):
    if isinstance(maps, np.ndarray) and maps.ndim == 3:
        maps = list(maps)
    if not isinstance(maps, (list, tuple)) or len(maps) < 2:
        raise ValueError("maps must be a list of at least 2 (n_i, 2) arrays")
    maps = [check_points(m, f"maps[{i}]") for i, m in enumerate(maps)]
    N = len(maps)
    if covs is None:
        covs = [None] * N
    elif not isinstance(covs, (list, tuple)) or len(covs) != N:
        raise ValueError(f"covs must be a list of {N} arrays, one per map")
    else:
        covs = [check_covariances(c, len(m), f"covs[{i}]") for i, (m, c) in enumerate(zip(maps, covs))]
    if sigma is None:
        if any(c is None for c in covs):
            raise ValueError("sigma is needed unless covs give every landmark's covariance")
        # One σ per map for the stages that take one: its RMS per-coordinate standard deviation.
        sigmas = [float(np.sqrt(np.mean(np.trace(c, axis1=1, axis2=2)) / 2)) for c in covs]
    elif np.ndim(sigma) == 0:
        sigmas = [check_sigma(sigma)] * N
    elif np.shape(sigma) == (N,):
        sigmas = [check_sigma(s, f"sigma[{i}]") for i, s in enumerate(sigma)]
    else:
        raise ValueError(f"sigma must be a number or one per map ({N},), got shape {np.shape(sigma)}")
    return maps, np.array(sigmas), covs


def candidate_pairs(maps, sigmas, candidates=None) -> np.ndarray:
    """The pairs (i, j), i < j, of maps to merge (see ``merge_many``'s ``candidates``).

    A pair's score counts its landmarks of nearly equal neighbourhoods: each
    landmark described by its distances to its ``DESCRIPTOR_NEIGHBOURS``
    nearest neighbours (sorted; invariant to rotation and translation), two
    descriptors close when within ``DESCRIPTOR_GATE`` times 2σ√k of each
    other (2σ: a distance difference's standard deviation), and the count
    divided by the product of the maps' sizes, since chance pairs grow with it.
    On 20-map teams of 100 landmarks (``make_group``, half-disc overlaps)
    each map's 6 best partners held 90-100 % of the pairs sharing 20 or more
    landmarks at 30 dB on chains and rings, 63-90 % at 20 dB and 74 % for the
    random topology (where maps have more such partners than 6): large teams
    may lose edges, so every pair is merged up to ``ALL_PAIRS_MAX_AGENTS``.
    """
    N = len(maps)
    everything = np.array([(i, j) for i in range(N) for j in range(i + 1, N)], dtype=np.intp)
    if candidates is None:
        candidates = "all" if N <= ALL_PAIRS_MAX_AGENTS else CANDIDATE_NEIGHBOURS
    if isinstance(candidates, str) and candidates == "all":
        return everything
    if not (isinstance(candidates, (int, np.integer)) and not isinstance(candidates, bool) and candidates >= 1):
        raise ValueError(f"candidates must be None, 'all' or a positive integer, got {candidates!r}")
    if candidates >= N - 1:
        return everything
    k = min(DESCRIPTOR_NEIGHBOURS, min(len(m) for m in maps) - 1)
    descriptors = np.concatenate([cKDTree(m).query(m, k + 1)[0][:, 1:] for m in maps])
    sizes = np.array([len(m) for m in maps])
    owner = np.repeat(np.arange(N), sizes)
    close = cKDTree(descriptors).query_pairs(DESCRIPTOR_GATE * 2 * float(np.max(sigmas)) * np.sqrt(k),
                                             output_type="ndarray")
    a, b = owner[close[:, 0]], owner[close[:, 1]]
    other = a != b
    count = np.bincount(np.minimum(a, b)[other] * N + np.maximum(a, b)[other], minlength=N * N).reshape(N, N)
    score = (count + count.T) / np.outer(sizes, sizes)
    np.fill_diagonal(score, -1)
    # Each map's best partners (ties to the lower index), then each pair once.
    best = np.argsort(-score, axis=1, kind="stable")[:, :int(candidates)]
    chosen = np.stack([np.repeat(np.arange(N), best.shape[1]), best.ravel()], axis=1)
    return np.unique(np.sort(chosen, axis=1), axis=0)


def pairwise_edges(maps, sigmas, covs, pairs, *, method=DEFAULT_METHOD, tau=DEFAULT_TAU, n_jobs=1, rng=None,
                   sigma_given=True) -> list:
    """``merge_maps`` of every listed pair of (valid) maps, as edges ("accepted" or "no match").

    Maps of one σ and no covariances merge with that σ; otherwise with both maps'
    covariances (σ² per coordinate where a map has none) and the RMS of their σ,
    or, when ``sigma_given`` is False, ``merge_maps``'s own pooled σ.
    """
    seeds = [None] * len(pairs) if rng is None else rng.spawn(len(pairs))
    jobs = []
    for (i, j), seed in zip(pairs, seeds):
        if covs[i] is None and covs[j] is None and sigmas[i] == sigmas[j]:
            noise = (sigmas[i], None, None)
        else:
            own = [np.full(len(maps[k]), sigmas[k] ** 2) if covs[k] is None else covs[k] for k in (i, j)]
            noise = (float(np.sqrt((sigmas[i] ** 2 + sigmas[j] ** 2) / 2)) if sigma_given else None, *own)
        jobs.append((maps[i], maps[j], *noise, tau, method, seed))
    if n_jobs == 1:
        results = [_merge_pair(*job) for job in jobs]
    else:
        try:
            from joblib import Parallel, delayed
        except ImportError as exc:
            raise ImportError("n_jobs other than 1 needs joblib: pip install 'mapmerge[parallel]'") from exc
        results = Parallel(n_jobs=n_jobs)(delayed(_merge_pair)(*job) for job in jobs)
    return [Edge(int(i), int(j), *r) for (i, j), r in zip(pairs, results)]


def _merge_pair(P, Q, sigma, cov_p, cov_q, tau, method, rng):
    res = merge_maps(P, Q, sigma, tau=tau, method=method, cov_p=cov_p, cov_q=cov_q, rng=rng)
    if not res.matched:
        return NO_MATCH, float("nan"), np.full(2, np.nan), np.full((3, 3), np.nan), res.pairs
    return ACCEPTED, float(res.theta), np.asarray(res.t, dtype=float), res.alignment.cov, res.pairs


# --- Rigid motions of the plane as (θ, t_x, t_y) with covariances ------------------------------------------


def compose(a, cov_a, b, cov_b):
    """``a ∘ b`` (b first) and its first-order covariance, a and b independent."""
    R = rotation(a[0])
    out = np.concatenate([[a[0] + b[0]], R @ b[1:] + a[1:]])
    Ja, Jb = np.eye(3), np.eye(3)
    Ja[1:, 0] = R @ ROT90 @ b[1:]
    Jb[1:, 1:] = R
    return out, Ja @ cov_a @ Ja.T + Jb @ cov_b @ Jb.T


def invert(a, cov_a):
    """The inverse motion and its first-order covariance."""
    Rt = rotation(-a[0])
    J = -np.eye(3)
    J[1:, 0] = Rt @ ROT90 @ a[1:]
    J[1:, 1:] = -Rt
    return np.concatenate([[-a[0]], -Rt @ a[1:]]), J @ cov_a @ J.T


# --- Assembly -------------------------------------------------------------------------------------------------


def assemble(maps, variances, edges, reference: int, placement: str) -> GroupMerge:
    """Place the maps from their pairwise edges, build the tracks and fuse (valid inputs).

    ``variances`` are each map's (n_i, 2, 2) landmark covariances. Returns the
    ``GroupMerge``; the edges come back with their final status.
    """
    N = len(maps)
    matched = [e for e in edges if e.matched]
    if placement == "joint":
        kept, refused = _consistent_edges(matched)
        edges = [e if not e.matched else _with_status(e, INCONSISTENT if id(e) in refused else ACCEPTED)
                 for e in edges]
        tree = kept
    else:
        kept = matched
        tree = _spanning_tree(matched, N) if placement == "tree" else _chain(matched, N)
    reference, poses, pose_cov = _place(N, tree, reference)
    placed = ~np.isnan(poses[:, 0])
    tracks = _tracks(maps, variances, [e for e in kept if placed[e.i] and placed[e.j]], poses, placed)
    if placement == "joint":
        poses, pose_cov, merged, merged_cov = _joint_ml(maps, variances, tracks, poses, pose_cov, reference)
    else:
        merged, merged_cov = _fuse(maps, variances, tracks, poses, pose_cov)
    return GroupMerge(reference=reference, placed=placed, theta=poses[:, 0], t=poses[:, 1:], frame_cov=pose_cov,
                      tracks=tracks, merged=merged, merged_cov=merged_cov, edges=edges, placement=placement)


def _with_status(e: Edge, status: str) -> Edge:
    return Edge(e.i, e.j, status, e.theta, e.t, e.cov, e.pairs)


def _edge_order(edges):
    """Strongest first: most correspondences, then the lower map indices."""
    return sorted(edges, key=lambda e: (-len(e.pairs), e.i, e.j))


def _consistent_edges(edges):
    """Greedy cycle-consistent edge set (module docstring, step 2): (kept edges, ids of refused ones)."""
    gate = chdtri(3, CYCLE_P)
    adjacency: dict[int, list] = {}
    group: dict[int, int] = {}
    kept, refused = [], set()
    for e in _edge_order(edges):
        gi, gj = group.get(e.i, e.i), group.get(e.j, e.j)
        motion = np.concatenate([[e.theta], e.t])
        if gi != gj:
            for node, g in list(group.items()) + [(e.j, gj)]:
                if g == gj:
                    group[node] = gi
            group.setdefault(e.i, gi)
            adjacency.setdefault(e.i, []).append((e.j, motion, e.cov))
            adjacency.setdefault(e.j, []).append((e.i, *invert(motion, e.cov)))
            kept.append(e)
            continue
        path, path_cov = _tree_motion(adjacency, e.i, e.j)
        r = np.concatenate([[wrap_angle(e.theta - path[0])], e.t - path[1:]])
        if r @ np.linalg.solve(e.cov + path_cov, r) <= gate:
            kept.append(e)
        else:
            refused.add(id(e))
    return kept, refused


def _tree_motion(adjacency, start: int, goal: int):
    """The motion from map ``start`` to map ``goal`` composed along the tree path, with its covariance."""
    previous = {start: None}
    queue = deque([start])
    while queue:
        node = queue.popleft()
        for nbr, motion, cov in adjacency.get(node, []):
            if nbr not in previous:
                previous[nbr] = (node, motion, cov)
                queue.append(nbr)
    steps = []
    node = goal
    while previous[node] is not None:
        parent, motion, cov = previous[node]
        steps.append((motion, cov))
        node = parent
    total, total_cov = np.zeros(3), np.zeros((3, 3))
    for motion, cov in reversed(steps):
        total, total_cov = compose(motion, cov, total, total_cov)
    return total, total_cov


def _spanning_tree(edges, N: int):
    """The maximum spanning forest of the edges by number of correspondences (ties as scipy breaks them)."""
    if not edges:
        return []
    i = np.array([e.i for e in edges])
    j = np.array([e.j for e in edges])
    w = np.array([len(e.pairs) for e in edges], dtype=float)
    # minimum_spanning_tree of (big - w): every weight stays positive, the order reversed.
    forest = minimum_spanning_tree(sparse.coo_matrix((w.max() + 1 - w, (i, j)), shape=(N, N))).tocoo()
    chosen = set(zip(forest.row.tolist(), forest.col.tolist()))
    return [e for e in edges if (e.i, e.j) in chosen]


def _chain(edges, N: int):
    """Sequential chaining: map k joins through its edge to the latest placed map that matched it."""
    by_pair = {(e.i, e.j): e for e in edges}
    placed, tree, waiting = [0], [], list(range(1, N))
    progress = True
    while waiting and progress:
        progress = False
        for k in list(waiting):
            link = next((by_pair.get((min(p, k), max(p, k))) for p in reversed(placed)
                         if (min(p, k), max(p, k)) in by_pair), None)
            if link is not None:
                tree.append(link)
                placed.append(k)
                waiting.remove(k)
                progress = True
    return tree


def _place(N: int, tree, reference: int):
    """Poses (N, 3) and covariances (N, 3, 3) of the maps the tree connects to the reference (NaN elsewhere)."""
    adjacency: dict[int, list] = {}
    for e in tree:
        motion = np.concatenate([[e.theta], e.t])
        adjacency.setdefault(e.i, []).append((e.j, motion, e.cov))
        adjacency.setdefault(e.j, []).append((e.i, *invert(motion, e.cov)))
    if reference not in adjacency and adjacency:
        # The reference joined nobody: the lowest-numbered map of the largest group.
        graph = sparse.coo_matrix((np.ones(len(tree)), ([e.i for e in tree], [e.j for e in tree])), shape=(N, N))
        _, label = connected_components(graph, directed=False)
        size = np.bincount(label)
        reference = max(sorted(adjacency), key=lambda k: (size[label[k]], -k))
    poses = np.full((N, 3), np.nan)
    cov = np.full((N, 3, 3), np.nan)
    poses[reference], cov[reference] = 0.0, 0.0
    queue = deque([reference])
    while queue:
        node = queue.popleft()
        for nbr, motion, c in adjacency.get(node, []):
            if np.isnan(poses[nbr, 0]):
                poses[nbr], cov[nbr] = compose(motion, c, poses[node], cov[node])
                poses[nbr, 0] = wrap_angle(poses[nbr, 0])
                queue.append(nbr)
    return reference, poses, cov


def _in_reference(poses, z, C, owner):
    """Landmark estimates z (O, 2) of maps ``owner`` with covariances C brought into the reference frame."""
    theta = poses[owner, 0]
    x = rotate(-theta, (z - poses[owner, 1:])[:, None, :])[:, 0]
    return x, covariance_in_p_frame(theta, C[:, None])[:, 0]


def _tracks(maps, variances, edges, poses, placed) -> np.ndarray:
    """Tracks (K, N) from the edges' correspondences (module docstring, step 3), ordered by their first landmark."""
    N = len(maps)
    sizes = np.array([len(m) for m in maps])
    offsets = np.concatenate([[0], np.cumsum(sizes)])
    owner = np.repeat(np.arange(N), sizes)
    row = np.arange(offsets[-1]) - offsets[owner]
    a = np.concatenate([offsets[e.i] + e.pairs[:, 0] for e in edges] + [np.empty(0, np.intp)]).astype(np.intp)
    b = np.concatenate([offsets[e.j] + e.pairs[:, 1] for e in edges] + [np.empty(0, np.intp)]).astype(np.intp)
    n_nodes = int(offsets[-1])
    graph = sparse.coo_matrix((np.ones(len(a)), (a, b)), shape=(n_nodes, n_nodes))
    _, label = connected_components(graph, directed=False)
    # Components holding two landmarks of one map are rebuilt closest link first.
    key = label * N + owner
    uniq, count = np.unique(key, return_counts=True)
    bad = np.unique(uniq[count > 1] // N)
    if bad.size:
        z, C = np.concatenate(maps), np.concatenate(variances)
        link = np.flatnonzero(np.isin(label[a], bad))
        x, Cx = _in_reference(np.nan_to_num(poses), z, C, owner)
        d = x[a[link]] - x[b[link]]
        d2 = np.einsum("ki,kij,kj->k", d, np.linalg.inv(Cx[a[link]] + Cx[b[link]]), d)
        root = {}

        def find(u):
            while root.get(u, u) != u:
                u = root[u]
            return u

        members = {}
        for k in link[np.argsort(d2, kind="stable")]:
            ra, rb = find(int(a[k])), find(int(b[k]))
            ma, mb = members.get(ra, {int(owner[ra])}), members.get(rb, {int(owner[rb])})
            if ra != rb and not ma & mb:
                root[rb] = ra
                members[ra] = ma | mb
        nodes = np.flatnonzero(np.isin(label, bad))
        label[nodes] = label.max() + 1 + np.array([find(int(u)) for u in nodes])
    keep = placed[owner]
    _, first, label = np.unique(label[keep], return_index=True, return_inverse=True)
    # Renumber tracks in the order of their first landmark (map, row).
    rank = np.empty(len(first), np.intp)
    rank[np.argsort(first, kind="stable")] = np.arange(len(first))
    tracks = np.full((len(first), N), -1, dtype=np.intp)
    tracks[rank[label], owner[keep]] = row[keep]
    return tracks


def _observations(maps, variances, tracks):
    """Track, map, estimate (O, 2) and covariance (O, 2, 2) of every landmark in ``tracks``."""
    k, owner = np.nonzero(tracks >= 0)
    offsets = np.concatenate([[0], np.cumsum([len(m) for m in maps])])
    flat = offsets[owner] + tracks[k, owner]
    return k, owner, np.concatenate(maps)[flat], np.concatenate(variances)[flat]


def _weighted_means(k, x, W, K):
    """Information-weighted mean (K, 2) and its covariance (K, 2, 2) of estimates x grouped by k."""
    info = np.zeros((K, 2, 2))
    np.add.at(info, k, W)
    vec = np.zeros((K, 2))
    np.add.at(vec, k, np.einsum("kij,kj->ki", W, x))
    cov = np.linalg.inv(info)
    return np.einsum("kij,kj->ki", cov, vec), cov


def _fuse(maps, variances, tracks, poses, pose_cov):
    """The baselines' fused map: each track's estimates in the reference frame, information-weighted,
    every estimate's covariance including its frame's (``mapped_covariance``)."""
    k, owner, z, C = _observations(maps, variances, tracks)
    x = np.empty_like(z)
    Cx = np.empty_like(C)
    for i in np.unique(owner):
        mine = owner == i
        x[mine] = rotate(-poses[i, 0], z[mine] - poses[i, 1:])
        Cx[mine] = mapped_covariance(x[mine], poses[i, 0], pose_cov[i], C[mine])
    return _weighted_means(k, x, np.linalg.inv(Cx), len(tracks))


def _joint_ml(maps, variances, tracks, poses, pose_cov, reference):
    """Joint ML of the placed frames and the landmarks seen twice or more (module docstring, step 4).

    Returns poses, their covariances, the fused map and its covariances.
    """
    N = len(maps)
    k_all, owner_all, z_all, C_all = _observations(maps, variances, tracks)
    seen = np.bincount(k_all, minlength=len(tracks))
    multi = seen[k_all] >= 2
    # Fused landmarks are numbered 0..K-1 among the tracks seen twice or more.
    k = (np.cumsum(seen >= 2) - 1)[k_all[multi]]
    owner, z, C = owner_all[multi], z_all[multi], C_all[multi]
    K = int((seen >= 2).sum())
    free = np.array([i for i in range(N) if not np.isnan(poses[i, 0]) and i != reference], dtype=np.intp)
    slot = np.full(N, -1)
    slot[free] = np.arange(len(free))
    system = _System(k, slot[owner], len(free), K)
    poses = poses.copy()
    W = np.linalg.inv(C)
    X, _ = _weighted_means(k, *_back_projected(poses, z, C, owner), K)
    scale = max(float(np.max(np.ptp(np.concatenate(maps), axis=0))), 1e-300)
    for _ in range(GN_MAX_ITER):
        S, dp, dx = system.step(poses, X, z, W, owner)
        poses[free] += dp
        X += dx
        if max(np.max(np.abs(dx), initial=0.0), np.max(np.abs(dp * [scale, 1, 1]), initial=0.0)) <= GN_TOL * scale:
            break
    S, _, _ = system.step(poses, X, z, W, owner)
    poses[free, 0] = wrap_angle(poses[free, 0])
    S_inv = np.linalg.inv(S)
    pose_cov = pose_cov.copy()
    pose_cov[free] = S_inv.reshape(len(free), 3, len(free), 3)[np.arange(len(free)), :, np.arange(len(free))]
    merged = np.empty((len(tracks), 2))
    merged_cov = np.empty((len(tracks), 2, 2))
    merged[seen >= 2], merged_cov[seen >= 2] = X, system.landmark_covariances(S_inv)
    single = ~multi
    ks, own, zs, Cs = k_all[single], owner_all[single], z_all[single], C_all[single]
    for i in np.unique(own):
        mine = own == i
        merged[ks[mine]] = rotate(-poses[i, 0], zs[mine] - poses[i, 1:])
        merged_cov[ks[mine]] = mapped_covariance(merged[ks[mine]], poses[i, 0], pose_cov[i], Cs[mine])
    return poses, pose_cov, merged, merged_cov


def _back_projected(poses, z, C, owner):
    x, Cx = _in_reference(poses, z, C, owner)
    return x, np.linalg.inv(Cx)


class _System:
    """Gauss-Newton's normal equations of the joint ML with the landmarks eliminated.

    Observation o (landmark k_o seen by the map in frame slot s_o, -1 for the
    reference) couples one frame and one landmark, so the Schur complement
    ``S = A - B D⁻¹ Bᵀ`` of the landmarks' 2x2 blocks D has a 3x3 block for
    every two observations of one landmark: those pairs are listed once.
    """

    def __init__(self, k, s, P, K):
        self.k, self.s, self.P, self.K = k, s, P, K
        self.free = np.flatnonzero(s >= 0)
        # Every ordered pair of free observations of one landmark.
        obs = self.free[np.argsort(k[self.free], kind="stable")]
        count = np.bincount(k[obs], minlength=K)
        start = np.cumsum(count) - count
        reps = count[k[obs]]
        first = np.repeat(obs, reps)
        within = np.arange(reps.sum()) - np.repeat(np.cumsum(reps) - reps, reps)
        self.pair = (first, obs[start[k[first]] + within])

    def step(self, poses, X, z, W, owner):
        """S (3P, 3P) at the current estimate, and the Gauss-Newton step (δ frames (P, 3), δ landmarks (K, 2))."""
        k, s, P, K, f = self.k, self.s, self.P, self.K, self.free
        theta = poses[owner, 0]
        c, sn = np.cos(theta), np.sin(theta)
        R = np.stack([np.stack([c, -sn], -1), np.stack([sn, c], -1)], -2)
        x = X[k]
        r = z - (np.einsum("oij,oj->oi", R, x) + poses[owner, 1:])
        norm = np.sqrt(np.einsum("oi,oij,oj->o", r, W, r))
        Ww = W * np.where(norm > HUBER_K, HUBER_K / np.maximum(norm, 1e-300), 1.0)[:, None, None]
        WR = Ww @ R
        D = np.zeros((K, 2, 2))
        np.add.at(D, k, R.transpose(0, 2, 1) @ WR)
        gx = np.zeros((K, 2))
        np.add.at(gx, k, np.einsum("oji,oj->oi", WR, r))
        self.Dinv = Dinv = np.linalg.inv(D)
        # Jacobian of R x + t in (θ, t): [R J x, I]; in x: R.
        Jp = np.concatenate([np.einsum("oij,jk,ok->oi", R[f], ROT90, x[f])[:, :, None],
                             np.broadcast_to(np.eye(2), (len(f), 2, 2))], axis=2)
        self.Bo = Bo = Jp.transpose(0, 2, 1) @ WR[f]  # (O_f, 3, 2): the frame-landmark blocks
        self.Y = Y = Bo @ Dinv[k[f]]  # B D⁻¹, per observation
        S = np.zeros((P, P, 3, 3))
        np.add.at(S, (s[f], s[f]), Jp.transpose(0, 2, 1) @ Ww[f] @ Jp)
        where = np.empty(len(z), np.intp)
        where[f] = np.arange(len(f))
        a, b = where[self.pair[0]], where[self.pair[1]]
        np.add.at(S, (s[self.pair[0]], s[self.pair[1]]), -(Y[a] @ Bo[b].transpose(0, 2, 1)))
        rhs = np.zeros((P, 3))
        np.add.at(rhs, s[f], np.einsum("oai,oab,ob->oi", Jp, Ww[f], r[f]) - np.einsum("oij,oj->oi", Y, gx[k[f]]))
        S = S.transpose(0, 2, 1, 3).reshape(3 * P, 3 * P)
        dp = np.linalg.solve(S, rhs.ravel()).reshape(P, 3) if P else np.zeros((0, 3))
        back = np.zeros((K, 2))
        np.add.at(back, k[f], np.einsum("oji,oj->oi", Bo, dp[s[f]]))
        return S, dp, np.einsum("kij,kj->ki", Dinv, gx - back)

    def landmark_covariances(self, S_inv):
        """Each landmark's covariance D⁻¹ + (B D⁻¹)ᵀ S⁻¹ (B D⁻¹), at the last ``step``'s linearisation."""
        k, s, f = self.k, self.s, self.free
        blocks = S_inv.reshape(self.P, 3, self.P, 3).transpose(0, 2, 1, 3)
        where = np.empty(len(k), np.intp)
        where[f] = np.arange(len(f))
        a, b = where[self.pair[0]], where[self.pair[1]]
        cov = self.Dinv.copy()
        np.add.at(cov, k[self.pair[0]], self.Y[a].transpose(0, 2, 1) @ blocks[s[self.pair[0]], s[self.pair[1]]]
                  @ self.Y[b])
        return cov

"""Outside baselines run through the same interface as the paper's matcher.

Each module holds one baseline with a batch function
``merge(P, Q, sigma, tri_p, tri_q, rng)`` returning a ``MergeBatch``:

- ``groth``: Groth (1986)'s invariant triangle matching with voting;
- ``astroalign``: ``astroalign.find_transform`` (optional extra ``[baselines]``);
- ``cpd``: rigid Coherent Point Drift (``pycpd``, optional extra ``[peers]``);
- ``clipper``, ``teaser``: CLIPPER's consistency-graph clique and TEASER++ (z = 0), built from their
  sources by ``tools/build_peers.sh`` (see docs/peers.md).
"""

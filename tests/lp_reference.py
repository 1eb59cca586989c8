"""The sparse LP by scipy's exact sparse assignment, the reference ``assign_sparse`` is checked against."""

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import min_weight_full_bipartite_matching


def lapjvsp_assign(log_lr, pairs, shape, objective="lr"):
    """``assignment.assign_sparse`` by LAPJVsp: each p row gets a private zero-gain dummy partner."""
    n_p, n_q = shape
    gain = np.exp(log_lr) if objective == "lr" else log_lr - log_lr.min()
    graph = coo_matrix((np.r_[gain + 1.0, np.ones(n_p)],
                        (np.r_[pairs[:, 0], np.arange(n_p)], np.r_[pairs[:, 1], n_q + np.arange(n_p)])),
                       shape=(n_p, n_q + n_p)).tocsr()
    r, c = min_weight_full_bipartite_matching(graph, maximize=True)
    return np.stack([r[c < n_q], c[c < n_q]], axis=1).astype(np.intp)

"""Compiled DBSCAN labelling from the eps-neighbour pairs (``slam.preprocess.dynamics``):
union-find over the core-core pairs instead of a sparse graph's connected components and a
sort of the border pairs (a 64-beam scan's ~27k voxel centroids make ~600k pairs: 54 ms of
numpy and scipy, ~5 ms here), the same labels."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def _root(parent, a):
    """Root of ``a`` in the union-find forest, halving the path on the way."""
    while parent[a] != a:
        parent[a] = parent[parent[a]]
        a = parent[a]
    return a


@njit(cache=True, nogil=True)
def dbscan_labels(n, i, j, min_samples):
    """DBSCAN labels (n,) int64 from the pairs (i[m], j[m]) of points within eps (each pair
    once): cores have >= min_samples points within eps (themselves included); clusters are
    the connected components of the cores numbered by their lowest core point; a border
    point takes the lowest cluster number among its core neighbours; noise is -1."""
    deg = np.ones(n, dtype=np.int64)
    for m in range(len(i)):
        deg[i[m]] += 1
        deg[j[m]] += 1
    core = deg >= min_samples
    parent = np.arange(n)
    for m in range(len(i)):
        a, b = i[m], j[m]
        if core[a] and core[b]:
            ra, rb = _root(parent, a), _root(parent, b)
            if ra != rb:  # the lower root wins: roots stay the lowest point of their tree
                if ra < rb:
                    parent[rb] = ra
                else:
                    parent[ra] = rb
    labels = np.full(n, -1, dtype=np.int64)
    number = np.full(n, -1, dtype=np.int64)  # root -> cluster number
    k = 0
    for a in range(n):  # ascending: a component is numbered at its first core point
        if core[a]:
            r = _root(parent, a)
            if number[r] < 0:
                number[r] = k
                k += 1
            labels[a] = number[r]
    for m in range(len(i)):  # border points: the lowest number among core neighbours
        a, b = i[m], j[m]
        if core[a] and not core[b]:
            if labels[b] < 0 or labels[a] < labels[b]:
                labels[b] = labels[a]
        elif core[b] and not core[a]:
            if labels[a] < 0 or labels[b] < labels[a]:
                labels[a] = labels[b]
    return labels

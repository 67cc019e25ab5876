"""Fill-reducing orderings for the sparse factorisations of tet-mesh matrices.

A sparse direct solver's memory and time are set by the fill of its factor, and the fill by the
order of the unknowns. SuperLU's own symmetric choice (minimum degree on A^T + A) is made for
general sparsity; on 3D meshes nested dissection fills far less: on the pinned 4:1:1 bar at
98k tets the shifted stiffness factored in 10 s with 6.0e7 nonzeros in L + U, against 47 s and
1.4e8 with MMD_AT_PLUS_A (one run of each on this 2-core machine).

``nested_dissection`` is the geometric kind: the mesh's nodes are split in two by the median of
their longest extent, the nodes of one half that touch the other become the separator, which is
numbered after both halves, and each half is split again until it is small. It needs only the
node positions and the node graph, so it works for any tet mesh (it never looks at the tets).

Shapes: points (N, 3) [m]; adjacency (N, N) sparse, nonzero where two nodes share a tet.
"""
import numpy as np
import scipy.sparse as sp

LEAF_SIZE = 32      # nodes in a part that is no longer split (16 to 64 fill about alike)


def node_graph(K, dofs_per_node=3):
    """(N, N) sparse node adjacency of a (d N, d N) matrix: nodes i, j are adjacent when any
    entry of their d x d block is nonzero."""
    K = sp.csr_matrix(K)
    n = K.shape[0] // dofs_per_node
    gather = sp.kron(sp.identity(n, format="csr"), np.ones((1, dofs_per_node)), format="csr")
    pattern = K.copy()
    pattern.data = np.ones_like(pattern.data)
    return (gather @ pattern @ gather.T).tocsr()


def nested_dissection(points, adjacency, leaf_size=LEAF_SIZE):
    """(N,) node order by geometric nested dissection (module docstring): a permutation p, so
    that node p[0] is numbered first. Deterministic: ties in the median split go to the lower
    half, and nothing is random."""
    return np.concatenate(nested_dissection_blocks(points, adjacency, leaf_size))


def nested_dissection_blocks(points, adjacency, leaf_size=LEAF_SIZE):
    """``nested_dissection`` as its blocks, in order: a list of non-empty int arrays of node
    indices (the leaves and separators), for a factorisation by blocks (``solver.cholesky``)."""
    points = np.asarray(points, dtype=np.float64)
    graph = sp.csr_matrix(adjacency)
    if graph.shape != (len(points), len(points)):
        raise ValueError(f"adjacency is {graph.shape} but there are {len(points)} points")
    order = []
    on_right = np.zeros(len(points), dtype=bool)

    def split(nodes):
        if len(nodes) <= leaf_size:
            order.append(nodes)
            return
        P = points[nodes]
        key = P[:, np.argmax(P.max(axis=0) - P.min(axis=0))]
        left = key <= np.median(key)
        if left.all() or not left.any():           # all on one coordinate: nothing to split
            order.append(nodes)
            return
        on_right[nodes[~left]] = True
        touches = graph[nodes[left]] @ on_right.astype(np.float64) > 0.0
        on_right[nodes[~left]] = False
        split(nodes[left][~touches])
        split(nodes[~left])
        order.append(nodes[left][touches])            # the separator goes last

    split(np.arange(len(points)))
    return [block for block in order if len(block)]


def dof_order(node_order, dofs_per_node=3):
    """(d N,) DOF permutation that keeps each node's d DOFs together, in ``node_order``."""
    node_order = np.asarray(node_order, dtype=np.int64)
    return (dofs_per_node * node_order[:, None] + np.arange(dofs_per_node)).ravel()

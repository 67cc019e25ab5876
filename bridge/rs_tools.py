"""Solver objects built from a prepared body on demand, kept in memory per prepared key.

Factorisations (the Poisson reconstruction, the pose transfer) are made once per body and reused
for every preview update and every interpolated frame.
"""
import collections
import functools

import numpy as np

from ..solver import rs, transfer
from . import bodies, staleness

_TOOLS = collections.OrderedDict()   # prepared key -> RSTools
_LIMIT = 8


class RSTools:
    def __init__(self, body):
        self.body = body
        self.nodes = body.tet_body.nodes
        self.tets = body.tet_body.tets
        self.embedding = body.tet_body.embedding            # positions: base = embedding @ nodes
        self.displacement_embedding = body.displacement_embedding   # displacements; pins hold

    @property
    def volumes(self):
        """(E,) unsigned tet volumes [m^3], kept on the tet body (read-only)."""
        return self.body.tet_body.volumes

    def lumped_masses(self, density):
        """(N,) lumped node masses [kg] for density [kg/m^3], kept on the tet body (read-only)."""
        return self.body.tet_body.lumped_masses(density)

    @functools.cached_property
    def pinned_nodes(self):
        return np.asarray(self.body.linear_modes.pinned_nodes, dtype=np.int64)

    @functools.cached_property
    def modal_rs(self):
        """(E, 9, r): linear RS coordinates of each mode, Q W."""
        Q = rs.rs_operator(self.nodes, self.tets)
        return rs.linear_rs(Q, self.body.linear_modes.vectors)

    @functools.cached_property
    def reconstruction(self):
        """Ψ honouring the body's pins (or its mean position for a free body)."""
        pins = self.pinned_nodes if len(self.pinned_nodes) else None
        return rs.PoissonReconstruction(self.nodes, self.tets, pinned_nodes=pins)

    @functools.cached_property
    def free_reconstruction(self):
        """Ψ with only the mean position fixed: for poses that move the pins."""
        return rs.PoissonReconstruction(self.nodes, self.tets)

    @functools.cached_property
    def neighbours(self):
        return rs.tet_neighbours(self.tets)

    @functools.cached_property
    def pose_transfer(self):
        return transfer.PoseTransfer(self.nodes, self.tets, self.embedding)

    @property
    def deformer(self):
        """The reduced RS deformer (None if the body was prepared without one)."""
        return self.body.deformer

    @functools.cached_property
    def surface_basis(self):
        """Φ B (3n, rB): base-vertex displacement per reduced coordinate, node-major rows."""
        B = self.deformer.basis
        N, rB = len(self.nodes), B.shape[1]
        return (self.displacement_embedding @ B.reshape(N, 3 * rB)).reshape(-1, rB)

    def surface(self, node_displacement):
        """(n, 3) base-vertex displacement of a node displacement (N, 3)."""
        return self.displacement_embedding @ node_displacement


def for_object(obj):
    """RSTools for the object's prepared body, or None if it is not prepared for this mesh (or
    is stale: see staleness.stale_reason)."""
    if staleness.stale_reason(obj, cached=True):
        return None
    key = obj.rs_elastic.prepared_key + obj.rs_elastic.reduced_key
    if key in _TOOLS:
        _TOOLS.move_to_end(key)
        return _TOOLS[key]
    body = bodies.load_prepared(obj)
    if body is None or body.tet_body.embedding.shape[0] != len(obj.data.vertices):
        return None
    tools = _TOOLS[key] = RSTools(body)
    while len(_TOOLS) > _LIMIT:
        _TOOLS.popitem(last=False)
    return tools

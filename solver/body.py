"""A prepared body as arrays: its tet mesh with the embedding of the render mesh (``TetBody``) and
what the preparation stages made of it (``PreparedBody``).

The tet body keeps what every user of it derives from the mesh alone (unsigned tet volumes,
lumped masses per density), computed once. Each stage object (``TetBody``,
``modes.LinearModes``, ``reduced.ReducedRS``, ``materials.ReducedPotential``) converts itself
with ``to_arrays()`` and back with the classmethod ``from_arrays(arrays)``, for cache files.
"""
import dataclasses
import functools

import numpy as np
import scipy.sparse as sp

from . import fem, materials, modes, reduced


@dataclasses.dataclass
class TetBody:
    nodes: np.ndarray        # (N, 3) float64, object space, metres
    tets: np.ndarray         # (E, 4) int64, positively oriented
    embedding: sp.csr_matrix  # (n, N) barycentric weights: base vertices = embedding @ nodes

    def to_arrays(self):
        """dict of numpy arrays for ``cache.save`` (the embedding as its csr parts)."""
        Phi = self.embedding
        return dict(nodes=self.nodes, tets=self.tets, phi_data=Phi.data, phi_indices=Phi.indices,
                    phi_indptr=Phi.indptr, phi_shape=np.asarray(Phi.shape))

    @classmethod
    def from_arrays(cls, arrays):
        """Inverse of ``to_arrays``."""
        Phi = sp.csr_matrix((arrays["phi_data"], arrays["phi_indices"], arrays["phi_indptr"]),
                            shape=tuple(int(n) for n in arrays["phi_shape"]))
        return cls(arrays["nodes"], arrays["tets"].astype(np.int64), Phi)

    @functools.cached_property
    def volumes(self):
        """(E,) unsigned tet volumes [m^3] (read-only)."""
        return _read_only(np.abs(fem.tet_volumes(self.nodes, self.tets)))

    def lumped_masses(self, density):
        """(N,) lumped node masses [kg] for density [kg/m^3] (``fem.lumped_masses``), computed
        once per density (read-only)."""
        by_density = self.__dict__.setdefault("_lumped_masses", {})
        if density not in by_density:
            by_density[density] = _read_only(fem.lumped_masses(self.nodes, self.tets, density))
        return by_density[density]


def _read_only(array):
    """The array, made read-only: it is shared by every caller."""
    array.flags.writeable = False
    return array


@dataclasses.dataclass
class PreparedBody:
    tet_body: TetBody
    linear_modes: modes.LinearModes
    deformer: reduced.ReducedRS = None      # None for a body prepared before reduced RS existed
    keys: tuple = ("", "", "")               # (tets, modes, reduced) keys it was made under
    digests: tuple = ("", "")                # content digests of (tet_body, linear_modes)
    energy: materials.ReducedPotential = None   # the energy cubature, if Prepare made one
    energy_key: str = ""
    # (n, N) csr: the embedding for displacements, with the pinned vertices held by pinned
    # nodes (embed.SurfacePins.embedding); None: the tet body's own (a free body)
    pinned_embedding: sp.csr_matrix = None

    @property
    def displacement_embedding(self):
        """(n, N) csr mapping node displacements to base-vertex displacements (pins hold)."""
        return self.tet_body.embedding if self.pinned_embedding is None else self.pinned_embedding

    def surface_mode(self, index):
        """(n, 3) displacement of the base vertices for mode `index` (0-based), mass-normalised."""
        w = self.linear_modes.vectors[:, index].reshape(-1, 3)
        return self.displacement_embedding @ w

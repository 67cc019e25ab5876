"""A prepared body as arrays: its tet mesh with the embedding of the render mesh (``TetBody``) and
what the preparation stages made of it (``PreparedBody``).

A prepared body also makes, on first use, the solver objects every user of it shares (the RS
coordinates of its modes, the Poisson reconstructions, the pose transfer, the surface basis Φ B):
their factorisations are made once per body and reused by every preview update, interpolated
frame, solve and simulation.

The tet body keeps what every user of it derives from the mesh alone (unsigned tet volumes,
lumped masses per density), computed once. Each stage object (``TetBody``,
``modes.LinearModes``, ``reduced.ReducedRS``, ``materials.ReducedPotential``) converts itself
with ``to_arrays()`` and back with the classmethod ``from_arrays(arrays)``, for cache files.
"""
import dataclasses
import functools

import numpy as np
import scipy.sparse as sp

from . import fem, materials, modes, reduced, rs, transfer


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
    # (E,) each tet's Young's modulus over the body's own (its value at weight 1 of a stiffness
    # group, ``preparation.stiffness_scale``); None: a uniform material. The modes were computed
    # with it, and every material made of the body (``material``) carries it.
    stiffness_scale: np.ndarray = None
    # The modes at 1 Pa and 1 kg/m^3 that linear_modes were moved from (``preparation.modes_at``)
    # and the uniform density [kg/m^3] they were moved to: what a cache trains in, so that no
    # change of Young's modulus or density trains it again. None: linear_modes themselves (at
    # ``density`` 1, the scale of a body made without them).
    unit_modes: modes.LinearModes = None
    density: float = 1.0

    @property
    def mode_scale(self):
        """The body's modes over ``unit_modes`` (1 / sqrt(density)): the scale that moves a
        quadrature trained in unit coordinates to the body's (``for_mode_scale``)."""
        return 1.0 if self.unit_modes is None else 1.0 / np.sqrt(float(self.density))

    def unit_modal_rs(self):
        """(E, 9, r) linear RS of ``unit_modes`` (``modal_rs`` itself when they are the body's
        modes or at 1 kg/m^3); computed on each call, not kept (it is as large as modal_rs)."""
        if self.unit_modes is None or self.mode_scale == 1.0:
            return self.modal_rs
        return rs.linear_rs(rs.rs_operator(self.nodes, self.tets), self.unit_modes.vectors)

    # --- the material, as every consumer makes it ---------------------------------------------
    def tet_youngs(self, youngs):
        """Young's modulus [Pa] of each tet for the body's Young's modulus ``youngs`` [Pa]: the
        number itself for a uniform body, (E,) for a painted one."""
        return youngs if self.stiffness_scale is None else youngs * self.stiffness_scale

    def material(self, kind, youngs, poisson, fung_stiffening=10.0):
        """The ``materials`` material ``kind`` (LINEAR, STVK, FUNG) of the body for its Young's
        modulus [Pa] and Poisson's ratio: per-tet Lame parameters over all its tets when it is
        painted. ValueError for an unstable material."""
        mu, lam = fem.lame_parameters(self.tet_youngs(youngs), poisson)
        return materials.make_material(kind, mu, lam, fung_stiffening=fung_stiffening)

    @property
    def displacement_embedding(self):
        """(n, N) csr mapping node displacements to base-vertex displacements (pins hold)."""
        return self.tet_body.embedding if self.pinned_embedding is None else self.pinned_embedding

    # --- the tet mesh, as every solver function takes it -------------------------------------
    @property
    def nodes(self):
        """(N, 3) rest node positions [m]."""
        return self.tet_body.nodes

    @property
    def tets(self):
        """(E, 4) int64 tets."""
        return self.tet_body.tets

    @property
    def embedding(self):
        """(n, N) csr barycentric weights: base vertices = embedding @ nodes."""
        return self.tet_body.embedding

    @property
    def volumes(self):
        """(E,) unsigned tet volumes [m^3] (read-only)."""
        return self.tet_body.volumes

    def lumped_masses(self, density):
        """(N,) lumped node masses [kg] for density [kg/m^3] (read-only)."""
        return self.tet_body.lumped_masses(density)

    @functools.cached_property
    def pinned_nodes(self):
        """(p,) int64 pinned node indices (empty for a free body)."""
        return np.asarray(self.linear_modes.pinned_nodes, dtype=np.int64)

    # --- solver objects made once per body ---------------------------------------------------
    @functools.cached_property
    def modal_rs(self):
        """(E, 9, r): linear RS coordinates of each mode, Q W."""
        return rs.linear_rs(rs.rs_operator(self.nodes, self.tets), self.linear_modes.vectors)

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
        """(E, 4) face neighbours of each tet (-1 on the boundary)."""
        return rs.tet_neighbours(self.tets)

    @functools.cached_property
    def pose_transfer(self):
        """Carries render-vertex poses to the tet nodes (``transfer.PoseTransfer``)."""
        return transfer.PoseTransfer(self.nodes, self.tets, self.embedding)

    @functools.cached_property
    def surface_basis(self):
        """Φ B (3n, rB): base-vertex displacement per reduced coordinate, node-major rows."""
        B = self.deformer.basis
        N, rB = len(self.nodes), B.shape[1]
        return (self.displacement_embedding @ B.reshape(N, 3 * rB)).reshape(-1, rB)

    # --- positions of the render mesh ------------------------------------------------------------
    def surface(self, node_displacement):
        """(n, 3) base-vertex displacement of a node displacement (N, 3)."""
        return self.displacement_embedding @ node_displacement

    def surface_mode(self, index):
        """(n, 3) displacement of the base vertices for mode `index` (0-based), mass-normalised."""
        return self.surface(self.linear_modes.vectors[:, index].reshape(-1, 3))

    def surface_positions(self, rest, inputs):
        """Base-vertex positions rest + Φ B q(z) of deformer inputs z.

        rest (n, 3) [m] the base vertices at rest; inputs (m,) one pose or (F, m) several.
        Returns (n, 3) or (F, n, 3).
        """
        inputs = np.asarray(inputs, dtype=np.float64)
        q = self.deformer.q_batch(np.atleast_2d(inputs))                        # (F, rB)
        positions = rest[None] + (q @ self.surface_basis.T).reshape(len(q), -1, 3)
        return positions[0] if inputs.ndim == 1 else positions

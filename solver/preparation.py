"""The preparation of a body, stage by stage, on arrays: what Prepare Body computes.

1. ``tet_mesh``: the surface fTetWild meshes (a simplified closed proxy of a dense surface,
   ``proxy``) and its tet mesh (``tetmesh``), with the render mesh embedded (``embed``).
2. ``surface_pins``: the pinned nodes and the embedding that holds pinned vertices
   (``embed.pin_surface``).
3. ``unit_stiffness_modes``: stiffness, lumped masses and the modes for the pins and
   Poisson's ratio at Young's modulus 1 Pa and density 1 kg/m^3 (a painted material's per-tet
   scale comes from ``stiffness_scale``); ``modes_at`` moves them to the body's Young's
   modulus and density, so a change of either alone computes nothing again (``linear_modes``:
   both).
4. ``reduced_deformer``: the reduced RS basis and its cubature (``reduced``) of those modes;
   ``deformer_at`` moves it to the body's density.
5. ``unit_energy_potential``: the energy cubature of a StVK or Fung material (``materials``)
   at 1 Pa in the coordinates of the modes at 1 kg/m^3; ``energy_at`` moves it to the body's
   Young's modulus and density.

Each stage is a plain function of the one before, so the Blender layer can cache each result
under its own content key, and the bench times exactly what Prepare runs.
"""
import dataclasses

import numpy as np

from . import embed, fem, materials, modes, proxy, reduced, rig, rs, tetmesh
from .body import PreparedBody, TetBody

# How the energy cubature is trained (``materials.prepare_potential``).
ENERGY_TRAINING = dict(num_poses=200, max_tets=200, tol=1e-4, max_rotation=np.pi / 2, seed=0)


@dataclasses.dataclass
class MeshingSettings:
    edge_length: float = 0.05          # fraction of the bounding-box diagonal
    envelope: float = 1e-3             # fraction of the bounding-box diagonal
    proxy_triangles: int = 0           # 0: ``proxy.triangle_budget`` of the edge length
    time_limit: float = tetmesh.DEFAULT_TIME_LIMIT   # [s] fTetWild may run (``tetmesh``)


@dataclasses.dataclass
class ReducedSettings:
    basis_size: int = 0                # 0: automatic (``reduced.default_basis_size``)
    cubature_tets: int = 150
    cubature_tolerance: float = 0.002
    training_poses: int = 80


def mesher_surface(V, F, settings, say=lambda fraction, message: None):
    """(V, F, closed) of the surface fTetWild meshes: (V, F) (m, 3) itself, or its simplified
    closed proxy when it has more triangles than the budget. ``closed`` is False when a dense
    surface could not be simplified (not a closed manifold), so it is meshed whole."""
    budget = settings.proxy_triangles or proxy.triangle_budget(V, F, settings.edge_length)
    closed = True
    if len(F) > budget:
        say(0.02, f"Simplifying {len(F):,} triangles to a {budget:,}-triangle proxy")
        V, F, closed = proxy.proxy_surface(V, F, budget)
    return V, F, closed


def tet_mesh(V, F, settings, should_cancel=None):
    """(X (N, 3), T (E, 4)) of fTetWild's tet mesh of the surface (V, F) (``mesher_surface``'s),
    within ``settings.time_limit`` seconds. Raises ``tetmesh.TetMeshError`` (``TetMeshTimeout``
    when out of time)."""
    return tetmesh.tetrahedralize(V, F, edge_length_fac=settings.edge_length,
                                  epsilon=settings.envelope, timeout=settings.time_limit,
                                  should_cancel=should_cancel)


def embedded(X, T, base_vertices):
    """The ``TetBody`` of a tet mesh with the render mesh's vertices (n, 3) embedded."""
    return TetBody(X, T, embed.embed_points(X, T, base_vertices))


def surface_pins(tet_body, base_vertices, base_triangles, pin_weights, envelope,
                 holds_volume=False):
    """``embed.SurfacePins`` of the render vertices' pin weights (n,) in [0, 1].

    holds_volume: a rig's Follow Rig weights hold the flesh they paint, so they are carried
    into the volume (``rig.node_values``), as its springs below 0.5 are. fTetWild's surface
    strays up to the envelope from the mesh: twice that still finds the tet-surface nodes of a
    painted face (``embed.PIN_TOLERANCE`` is this for the default envelope).
    """
    X, T, Phi = tet_body.nodes, tet_body.tets, tet_body.embedding
    carried = rig.node_values(Phi, pin_weights, X, T)[:, 0] if holds_volume else None
    return embed.pin_surface(X, T, Phi, base_vertices, base_triangles, pin_weights,
                             threshold=embed.PIN_THRESHOLD, tolerance=2.0 * envelope,
                             node_weights=carried)


def tet_weights(tet_body, vertex_weights):
    """(E,) weight of each tet in [0, 1] from the render vertices' weights (n,) of a vertex
    group: carried to the tet nodes through the embedding and harmonically into the volume
    (``rig.node_values``, as a rig's Follow Rig weights are), and each tet's the mean of its
    four nodes'."""
    X, T = tet_body.nodes, tet_body.tets
    nodes = rig.node_values(tet_body.embedding, vertex_weights, X, T)[:, 0]
    return np.clip(nodes[T].mean(axis=1), 0.0, 1.0)


def stiffness_scale(tet_body, vertex_weights, ratio):
    """(E,) each tet's Young's modulus over the body's (``PreparedBody.stiffness_scale``) for a
    stiffness group painted with vertex_weights (n,) (vertices outside it 0) and ``ratio``, the
    Young's modulus at weight 0 over that at weight 1: ``fem.painted_youngs`` of ``tet_weights``.
    ValueError for a ratio that is not a positive number."""
    return fem.painted_youngs(1.0, ratio, tet_weights(tet_body, vertex_weights))


def unit_stiffness_modes(tet_body, poisson, count, pinned=None, stiffness_scale=None,
                         progress=lambda fraction, message: None):
    """``modes.LinearModes`` of the tet body at Young's modulus 1 Pa (times a painted body's
    per-tet ``stiffness_scale`` (E,), ``PreparedBody.stiffness_scale``), Poisson's ratio and
    density 1 kg/m^3, with the nodes ``pinned`` (p,) held (None: free); progress as in
    ``modes.linear_modes``.

    K is linear in Young's modulus and M in a uniform density, so the modes of a body are
    these with their eigenvalues times E / rho and their vectors times 1 / sqrt(rho)
    (``modes_at``): a change of Young's modulus or density reuses them, and the reduced stage
    built on them (``deformer_at``), instead of computing them again.
    ValueError when the pins hold every node or the material is not stable."""
    if pinned is not None and len(pinned) >= len(tet_body.nodes):
        raise ValueError("the pins hold every tet node: nothing is left free to move")
    scale = 1.0 if stiffness_scale is None else stiffness_scale
    K = fem.stiffness_matrix(tet_body.nodes, tet_body.tets, scale, poisson)
    return modes.linear_modes(K, tet_body.lumped_masses(1.0), count, pinned,
                              rest_positions=tet_body.nodes, progress=progress)


def linear_modes(tet_body, youngs, poisson, density, count, pinned=None, stiffness_scale=None,
                 progress=lambda fraction, message: None):
    """``modes.LinearModes`` for Young's modulus ``youngs`` [Pa] (a painted body's at weight 1,
    its per-tet ``stiffness_scale`` (E,) times that) and density [kg/m^3]:
    ``unit_stiffness_modes``, moved there (``modes_at``)."""
    _check_youngs(youngs)                   # before the eigensolve, not after it
    _check_density(density)
    return modes_at(unit_stiffness_modes(tet_body, poisson, count, pinned, stiffness_scale,
                                         progress), youngs, density)


def modes_at(unit_modes, youngs, density):
    """``unit_stiffness_modes``' result at Young's modulus ``youngs`` [Pa] and density
    [kg/m^3] (``LinearModes.for_material``). ValueError for either not a positive number."""
    _check_youngs(youngs)
    _check_density(density)
    return unit_modes.for_material(youngs, density)


def _check_youngs(youngs):
    if not np.isfinite(youngs) or not youngs > 0.0:
        raise ValueError(f"Young's modulus must be a positive number of pascals, got {youngs!r}")


def _check_density(density):
    if not np.isfinite(density) or not density > 0.0:
        raise ValueError(f"Density must be a positive number of kg/m³, got {density!r}")


def cubature_size(settings, num_nodes, num_tets, num_modes):
    """Cubature tets: the setting, raised to ``reduced.default_cubature_size`` of the automatic
    basis when the basis size is automatic, since that basis grows as O(modes^2)."""
    if settings.basis_size:
        return settings.cubature_tets
    automatic = reduced.default_basis_size(num_modes, num_nodes=num_nodes, num_tets=num_tets)
    return max(settings.cubature_tets, reduced.default_cubature_size(automatic, num_tets=num_tets))


def reduced_deformer(tet_body, unit_modes, settings, progress=lambda fraction, message: None):
    """The reduced RS deformer (``reduced.ReducedRS``) of ``unit_stiffness_modes``' modes,
    trained on poses up to 180 deg; progress(fraction in [0, 1], message). The training is
    the same for any Young's modulus and density (its poses are sized in radians and strain,
    the eigenvalues only weigh the modes relative to each other, and B is orthonormal in the
    mass of 1 kg/m^3): ``deformer_at`` moves it to the body's density."""
    X, T = tet_body.nodes, tet_body.tets
    pinned = unit_modes.pinned_nodes
    recon = rs.PoissonReconstruction(X, T, pinned_nodes=pinned if len(pinned) else None)
    deformer, _ = reduced.prepare_reduced_rs(
        X, T, tet_body.lumped_masses(1.0), unit_modes.vectors, unit_modes.eigenvalues,
        recon, max_size=settings.basis_size or None,
        max_tets=cubature_size(settings, len(X), len(T), unit_modes.vectors.shape[1]),
        tol=settings.cubature_tolerance, num_poses=settings.training_poses, progress=progress)
    return deformer


def deformer_at(unit_deformer, density):
    """``reduced_deformer``'s deformer for the body's modes at density [kg/m^3] (``modes_at``:
    the unit modes times 1 / sqrt(rho)): ``ReducedRS.for_mode_scale``."""
    _check_density(density)
    return unit_deformer.for_mode_scale(1.0 / np.sqrt(float(density)))


def unit_energy_potential(body, kind, poisson, fung_stiffening=10.0,
                          progress=lambda fraction, message: None):
    """The energy cubature (``materials.ReducedPotential``) of a StVK or Fung material of the
    prepared body, trained as ``ENERGY_TRAINING`` says at 1 Pa in the coordinates of
    ``body.unit_modes`` (1 kg/m^3; the body's own modes if it has none). Both energies are
    proportional to Young's modulus, and a density only rescales the modal coordinates, so one
    training serves every modulus and density (``energy_at`` moves it), bit for bit whatever
    the ones it was first asked for."""
    unit = body.material(kind, 1.0, poisson, fung_stiffening=fung_stiffening)
    modes_ = body.linear_modes if body.unit_modes is None else body.unit_modes
    potential, _ = materials.prepare_potential(
        unit, body.unit_modal_rs(), body.volumes, eigenvalues=modes_.eigenvalues,
        **ENERGY_TRAINING, progress=progress)
    return potential


def energy_potential(body, kind, youngs, poisson, fung_stiffening=10.0,
                     progress=lambda fraction, message: None):
    """``unit_energy_potential`` at the body's Young's modulus ``youngs`` [Pa] and density
    (``energy_at``)."""
    return energy_at(unit_energy_potential(body, kind, poisson, fung_stiffening, progress),
                     body, kind, youngs, poisson, fung_stiffening)


def energy_at(unit_potential, body, kind, youngs, poisson, fung_stiffening=10.0):
    """``unit_energy_potential``'s cubature moved to Young's modulus ``youngs`` [Pa] (the body's
    material at that modulus) and the body's modal coordinates (``body.mode_scale``); the
    same tets and weights."""
    _check_youngs(youngs)
    return unit_potential.for_mode_scale(body.mode_scale).with_material(
        body.material(kind, youngs, poisson, fung_stiffening=fung_stiffening))


def prepare_body(X, T, base_vertices, youngs, poisson, density, num_modes, pinned=None,
                 pinned_embedding=None, settings=None, stiffness=None):
    """A ``PreparedBody`` of a tet mesh in one call (no cache): the render vertices (n, 3)
    embedded; pinned (p,) node indices held (None: a free body) and pinned_embedding the
    render vertices' displacement embedding that holds them (``embed.SurfacePins``; None: the
    plain embedding); settings the ``ReducedSettings`` (defaults if None); stiffness None for a
    uniform material, or (vertex weights (n,), ratio) of a stiffness group (``stiffness_scale``)."""
    tet_body = embedded(X, T, base_vertices)
    scale = None if stiffness is None else stiffness_scale(tet_body, *stiffness)
    unit = unit_stiffness_modes(tet_body, poisson, num_modes, pinned, scale)
    deformer = deformer_at(reduced_deformer(tet_body, unit, settings or ReducedSettings()),
                           density)
    linear = modes_at(unit, youngs, density)
    return PreparedBody(tet_body, linear, deformer, pinned_embedding=pinned_embedding,
                        stiffness_scale=scale, unit_modes=unit, density=float(density))

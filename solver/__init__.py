"""Blender-free numerical core of RS Elastic.

Plain numpy / scipy / libigl functions on arrays, one concept per module:

- ``fem``      linear-tetrahedron finite elements: gradient operator G, stiffness K, lumped mass.
- ``modes``    linear modal analysis (K w = lambda M w), free or pinned bodies.
- ``ordering`` nested-dissection orders of tet-mesh matrices (fill-reducing, by blocks).
- ``cholesky`` supernodal sparse Cholesky over those blocks (the modes' shift-invert solves).
- ``embed``    barycentric embedding of render-mesh vertices in the tet mesh (sparse Phi).
- ``proxy``    a simplified closed proxy of a dense surface, for fTetWild.
- ``tetmesh``  fTetWild tetrahedralisation, run in a separate process (``tetwild_worker``) so a
  crash cannot kill Blender.
- ``rs``       rotation-strain coordinates: Q, polar/log/exp, Jacobians, Poisson reconstruction Ψ.
- ``transfer`` carries a pose of the render mesh over to the tet nodes.
- ``reduced``  reduced RS: the basis B, per-tet projections, the deformer z -> q -> u = B q.
- ``cubature`` training poses and greedy NNLS cubature (An et al. 2008).
- ``threads``  ordered parallel map for the reduced stage's per-pose work.
- ``accuracy`` after a solve: distance of the reduced model from full RS, stretch the targets ask.
- ``spacetime`` space-time editing with material optimisation (Gauss-Newton on banded systems).
- ``materials`` linear, StVK and Fung materials on the Cauchy strain; the reduced potential V(s).
- ``dynamics`` subspace dynamics in RS coordinates: the simulation, its state and step retries.
- ``integrators`` the time integration schemes (Newmark, implicit Euler), each chosen once.
- ``frames``   fixed, keyed and free body frames: mass moments and the inertia of a step in each.
- ``newton``   Newton / line search of one step's objective, with the RS map's curvature.
- ``body_contact`` a simulated body's contact samples: world positions, energy terms, guesses.
- ``inversion`` a volume barrier on the RS strain that keeps reduced bodies from inverting.
- ``rig``      flesh on a rig: elastic motion as a deviation from linear blend skinning.
- ``contact``  barrier, friction and damping contact of surface samples with mesh colliders.
- ``body``     a prepared body as arrays: its tets and embedding (volumes, lumped masses kept),
  the stages' results, and the solver objects made once per body (modal RS, reconstructions,
  pose transfer, Φ B); each stage object has ``to_arrays`` / ``from_arrays``.
- ``preparation`` the preparation, stage by stage: mesher surface, tets, pins, modes, reduced
  RS, energy cubature (what Prepare Body computes and the bench times).
- ``problems`` the space-time problem and the simulation, built from a prepared body and
  plain inputs (handle tracks, pose keys, a take; a material's potential and the loads).
- ``poses``    render-mesh poses through a body's RS coordinates: modal fits, in-betweens.
- ``cache``    content-keyed, atomically written ``.npz`` cache files.
- ``meshgen``  structured box tet meshes (tests and benchmarks).

Nothing in this package imports ``bpy`` or ``mathutils``; Blender code converts its data to
numpy arrays and calls in. Units: metres, kilograms, seconds, pascals (see SPEC.md).
"""

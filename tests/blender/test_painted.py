"""A painted material end to end (issue 28, item 2): `obj.rs_elastic.stiffness_group` and
`stiffness_ratio` set the Young's modulus of each tet.

Oracles: the full-space FEM of the prepared body's own tets with each tet's Young's modulus,
assembled in this file (scipy.sparse.linalg.eigsh shift-invert for the frequencies, a sparse
solve for the static sag); the
order of the sags of the uniform stiff, the painted and the uniform soft bar; the keys and the
fingerprint; the fault suite's one-line refusals that change nothing.
"""
import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import bpy

from blender_helpers import make_active, make_bar, user_fingerprint, vertices
from test_faults import refusal

YOUNGS = 3.0e7
RATIO = float(np.float32(1.0 / 3.0))   # as the float property holds it
PAINTED_UP_TO = 3.0     # vertices beyond x = 3 m are outside the group: weight 0


def stiffness_weights(rest):
    """(n,) what the test paints: 1 - x / 5 up to x = 3 m, 0 outside the group (the tip), as
    the float32 values a vertex group holds."""
    painted = np.where(rest[:, 0] <= PAINTED_UP_TO + 1e-9, 1.0 - rest[:, 0] / 5.0, 0.0)
    return painted.astype(np.float32).astype(np.float64)


def painted_bar(name="Bar", ratio=RATIO):
    """The 4 x 1 x 1 m bar pinned at x = 0 with its root painted stiff and its tip soft."""
    obj = make_bar(name=name, cuts=3)
    settings = obj.rs_elastic
    settings.edge_length, settings.num_modes, settings.youngs_modulus = 0.1, 6, YOUNGS
    group = obj.vertex_groups.new(name="Stiff")
    rest = vertices(obj)
    for index, weight in enumerate(stiffness_weights(rest)):
        if rest[index, 0] <= PAINTED_UP_TO + 1e-9:
            group.add([index], float(weight), 'REPLACE')
    settings.stiffness_group, settings.stiffness_ratio = "Stiff", ratio
    return obj


def reference_stiffness(X, T, tet_youngs, poisson):
    """csr K (3N, 3N) = sum_e V_e B_e^T D_e B_e for per-tet tet_youngs (E,) [Pa], assembled
    here (Voigt strains, shape functions from inverting [1 x y z], the textbook isotropic D_e),
    not by the extension's fem."""
    n_tets = len(T)
    P = np.concatenate([np.ones((n_tets, 4, 1)), X[T]], axis=2)
    grads = np.transpose(np.linalg.inv(P)[:, 1:, :], (0, 2, 1))       # (E, 4, 3)
    volumes = np.abs(np.linalg.det(P)) / 6.0
    gx, gy, gz = grads[..., 0], grads[..., 1], grads[..., 2]
    B = np.zeros((n_tets, 6, 12))                                      # [xx yy zz 2xy 2yz 2xz]
    B[:, 0, 0::3], B[:, 1, 1::3], B[:, 2, 2::3] = gx, gy, gz
    B[:, 3, 0::3], B[:, 3, 1::3] = gy, gx
    B[:, 4, 1::3], B[:, 4, 2::3] = gz, gy
    B[:, 5, 0::3], B[:, 5, 2::3] = gz, gx
    scale = tet_youngs / ((1.0 + poisson) * (1.0 - 2.0 * poisson))
    D = np.zeros((n_tets, 6, 6))
    D[:, :3, :3] = (scale * poisson)[:, None, None]
    D[:, [0, 1, 2], [0, 1, 2]] = (scale * (1.0 - poisson))[:, None]
    D[:, [3, 4, 5], [3, 4, 5]] = (scale * (1.0 - 2.0 * poisson) / 2.0)[:, None]
    K_e = volumes[:, None, None] * np.einsum("eki,ekl,elj->eij", B, D, B)
    dofs = (3 * T[:, :, None] + np.arange(3)).reshape(n_tets, 12)
    rows, cols = np.broadcast_arrays(dofs[:, :, None], dofs[:, None, :])
    return sp.coo_matrix((K_e.ravel(), (rows.ravel(), cols.ravel())),
                         shape=(3 * len(X),) * 2).tocsr()


def reference_masses(X, T, density):
    """(N,) lumped masses [kg]: a quarter of each tet's mass on each of its nodes."""
    volumes = np.abs(np.linalg.det(X[T[:, 1:]] - X[T[:, :1]])) / 6.0
    masses = np.zeros(len(X))
    np.add.at(masses, T, np.repeat(density * volumes[:, None] / 4.0, 4, axis=1))
    return masses


def painted_tet_youngs(ext, body, weights, ratio):
    """(E,) YOUNGS * ratio ** (1 - w_e) [Pa], w_e the mean of the tet's nodes' share of the
    painted vertex weights (n,) (``rig.node_values``)."""
    X, T = body.nodes, body.tets
    nodes = ext.solver.rig.node_values(body.tet_body.embedding, weights, X, T)[:, 0]
    return YOUNGS * ratio ** (1.0 - np.clip(nodes[T].mean(axis=1), 0.0, 1.0))


def full_space(ext, obj, body, weights, ratio):
    """(K (3N, 3N) csr of the body's own tets with each tet's Young's modulus, lumped masses
    (N,), free degrees of freedom), assembled here, each tet's modulus ``painted_tet_youngs``."""
    X, T = body.nodes, body.tets
    settings = obj.rs_elastic
    K = reference_stiffness(X, T, painted_tet_youngs(ext, body, weights, ratio),
                            settings.poisson_ratio)
    masses = reference_masses(X, T, settings.density)
    pinned = (3 * body.pinned_nodes[:, None] + np.arange(3)).ravel()
    return K, masses, np.setdiff1d(np.arange(3 * len(X)), pinned)


def reference_frequencies(K, masses, free, count):
    """(count,) lowest frequencies [Hz] of K u = lam M u on the free dofs (shift-invert)."""
    M = sp.diags(np.repeat(masses, 3)[free])
    values = spla.eigsh(K[free][:, free].tocsc(), k=count, M=M, sigma=0.0, which="LM",
                        return_eigenvectors=False)
    return np.sqrt(np.sort(values)) / (2.0 * np.pi)


def test_painted_frequencies_are_the_full_space_fem_of_the_same_tets(ext):
    obj = painted_bar()
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    body = ext.bridge.prepared.require(obj)
    weights = stiffness_weights(vertices(obj))
    K, masses, free = full_space(ext, obj, body, weights, RATIO)
    reference = reference_frequencies(K, masses, free, 6)
    prepared = body.linear_modes.frequencies_hz
    error = np.abs(prepared / reference - 1.0).max()
    shown = np.abs(np.array(obj.rs_elastic.frequencies) / reference - 1.0).max()
    print("painted frequencies [Hz]:", np.array2string(prepared, precision=5))
    print(f"against the full-space FEM: {error:.1e} (panel's float32 values {shown:.1e})")
    assert error < 1e-6 and shown < 1e-6
    np.testing.assert_allclose(body.tet_youngs(YOUNGS),
                               painted_tet_youngs(ext, body, weights, RATIO), rtol=1e-12)
    # Outside the group is weight 0: painting the tip's vertices too would give other modes.
    whole = np.where(vertices(obj)[:, 0] <= 4.0 + 1e-9, 1.0 - vertices(obj)[:, 0] / 5.0, 0.0)
    other = reference_frequencies(*full_space(ext, obj, body, whole, RATIO), 6)
    uniform = reference_frequencies(*full_space(ext, obj, body, np.ones(len(weights)), RATIO), 6)
    assert np.abs(other / reference - 1.0).max() > 1e3 * error
    assert np.all(prepared < 0.97 * uniform)


def stale_message(ext, obj):
    bpy.context.view_layer.update()
    return ext.bridge.staleness.stale_reason(obj, cached=True)


def repaint_the_root(obj):
    obj.vertex_groups["Stiff"].add([int(np.argmin(vertices(obj)[:, 0]))], 0.5, 'REPLACE')


def test_ratio_weights_and_group_are_in_the_fingerprint_and_the_keys(ext):
    obj = painted_bar()
    settings = obj.rs_elastic
    settings.material_model = 'STVK'          # Prepare trains its energy cubature too
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    stage_cache = ext.bridge.stage_cache
    keys = [(settings.prepared_key, stage_cache.energy_record(settings)["parent"])]
    assert ext.bridge.staleness.stale_reason(obj, cached=True) is None
    changes = [
        (lambda: setattr(settings, "stiffness_ratio", 0.5),
         "the stiffness ratio changed since Prepare Body: prepare again"),
        (lambda: repaint_the_root(obj),
         "the stiffness group changed since Prepare Body: prepare again"),
        (lambda: setattr(settings, "stiffness_group", ""),
         "the stiffness group changed since Prepare Body: prepare again"),
    ]
    for change, message in changes:
        change()
        assert stale_message(ext, obj) == message
        with pytest.raises(RuntimeError, match="prepare again"):
            bpy.ops.rs_elastic.simulate()
        assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
        assert stale_message(ext, obj) is None
        keys.append((settings.prepared_key, stage_cache.energy_record(settings)["parent"]))
    assert len({modes for modes, _ in keys}) == len(keys)        # every change: new modes key
    assert len({parent for _, parent in keys}) == len(keys)      # and a new energy cubature
    # Uniform: the ratio is not read, so it changes nothing.
    settings.stiffness_ratio = 0.2
    assert stale_message(ext, obj) is None
    # A renamed group is named, as a pin group is.
    settings.stiffness_group = "Stiff"
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    obj.vertex_groups["Stiff"].name = "Hard"
    assert stale_message(ext, obj) == ("stiffness group 'Stiff' no longer exists (renamed or "
                                       "deleted since Prepare Body): set Stiffness Group and "
                                       "prepare again")


def settled_tip_sag(ext, obj):
    """The tip's sag [m] on the first frame of a settled simulation, and the full-space static
    sag of the prepared tets under the same gravity (K(E_e) u = f)."""
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    assert bpy.ops.rs_elastic.simulate() == {'FINISHED'}
    bpy.context.scene.frame_set(1)
    rest = vertices(obj)
    tip = rest[:, 0] > 4.0 - 1e-9
    depsgraph = bpy.context.evaluated_depsgraph_get()
    mesh = obj.evaluated_get(depsgraph).data
    co = np.empty(len(mesh.vertices) * 3)
    mesh.vertices.foreach_get("co", co)
    simulated = rest[tip, 2].mean() - co.reshape(-1, 3)[tip, 2].mean()
    settings = obj.rs_elastic
    body = ext.bridge.prepared.require(obj)
    weights = (stiffness_weights(rest) if settings.stiffness_group
               else np.ones(len(rest)))
    ratio = settings.stiffness_ratio if settings.stiffness_group else 1.0
    youngs = settings.youngs_modulus
    K, masses, free = full_space(ext, obj, body, weights, ratio)
    K = K * (youngs / YOUNGS)
    force = np.zeros((len(masses), 3))
    force[:, 2] = -9.81 * masses
    u = np.zeros(3 * len(masses))
    u[free] = spla.spsolve(K[free][:, free].tocsc(), force.ravel()[free])
    full = -body.surface(u.reshape(-1, 3))[tip, 2].mean()
    return simulated, full


def test_a_bar_stiff_at_the_root_sags_between_the_uniform_stiff_and_soft_bars(ext):
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 1, 3
    obj = painted_bar()
    settings = obj.rs_elastic
    settings.start_settled = True
    sags = {}
    sags["painted"] = settled_tip_sag(ext, obj)
    for model in ('STVK', 'FUNG'):        # their energy cubatures are trained on the paint too
        settings.material_model = model
        sags[f"painted {model}"] = settled_tip_sag(ext, obj)
    settings.material_model = 'LINEAR'
    settings.stiffness_group = ""
    sags["stiff"] = settled_tip_sag(ext, obj)
    settings.youngs_modulus = YOUNGS * RATIO
    sags["soft"] = settled_tip_sag(ext, obj)
    for name, (simulated, full) in sags.items():
        print(f"{name}: settled tip sag {simulated:.4f} m, full-space static {full:.4f} m")
    stiff, painted, soft = (sags[name][0] for name in ("stiff", "painted", "soft"))
    assert 1.1 * stiff < painted < soft / 1.1
    for simulated, full in sags.values():       # the simulation uses the painted potential
        assert abs(simulated / full - 1.0) < 0.05   # (StVK and Fung: Linear at small strain)


def test_a_saved_painted_body_reopens_prepared_with_its_paint(ext, tmp_path):
    obj = painted_bar()
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    body = ext.bridge.prepared.require(obj)
    scale, frequencies = body.stiffness_scale.copy(), body.linear_modes.frequencies_hz.copy()
    key = obj.rs_elastic.prepared_key
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "painted.blend"))
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}     # its cache next to the file
    bpy.ops.wm.save_mainfile()
    bpy.ops.wm.read_homefile(use_empty=True)
    ext.bridge.stage_cache._MEMORY.clear()
    ext.bridge.prepared._BODIES.clear()
    ext.bridge.stage_cache.stats.clear()
    bpy.ops.wm.open_mainfile(filepath=str(tmp_path / "painted.blend"))
    obj = bpy.data.objects["Bar"]
    make_active(obj)
    settings = obj.rs_elastic
    assert (settings.stiffness_group, settings.stiffness_ratio) == ("Stiff", pytest.approx(RATIO))
    assert ext.bridge.staleness.stale_reason(obj) is None and settings.prepared_key == key
    reopened = ext.bridge.prepared.require(obj)
    np.testing.assert_array_equal(reopened.stiffness_scale, scale)
    np.testing.assert_array_equal(reopened.linear_modes.frequencies_hz, frequencies)
    assert ext.bridge.stage_cache.stats["modes"] == 0          # loaded, not computed


# --- refusals: one line, nothing changed (the fault suite's terms) -----------------------------------

def missing_group():
    painted_bar().rs_elastic.stiffness_group = "Nope"


def ratio(value):
    return lambda: setattr(painted_bar().rs_elastic, "stiffness_ratio", value)


REFUSALS = [
    ("missing stiffness group", missing_group, "Stiffness group 'Nope' does not exist on 'Bar'"),
    ("ratio 0", ratio(0.0), "Stiffness ratio must be above 0, got 0"),
    ("ratio negative", ratio(-0.5), "Stiffness ratio must be above 0, got -0.5"),
    ("ratio nan", ratio(float("nan")), "'Bar': Stiffness Ratio is nan; it must be a finite number"),
    ("ratio inf", ratio(float("inf")), "'Bar': Stiffness Ratio is inf; it must be a finite number"),
    ("ratio beyond the material limit", ratio(1e6),
     "Stiffness ratio × Young's modulus must be at most 1e+13 Pa, got 3e+13 Pa"),
]


@pytest.mark.parametrize("setup, message", [pytest.param(*row[1:], id=row[0]) for row in REFUSALS])
def test_a_bad_painted_material_is_refused(setup, message):
    setup()
    assert refusal(bpy.ops.rs_elastic.prepare) == message


def test_a_prepared_body_whose_stiffness_group_was_deleted_is_refused(ext):
    obj = painted_bar()
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    obj.vertex_groups.remove(obj.vertex_groups["Stiff"])
    bpy.context.view_layer.update()
    before = user_fingerprint()
    message = ("'Bar': stiffness group 'Stiff' no longer exists (renamed or deleted since "
               "Prepare Body): set Stiffness Group and prepare again")
    for operator in (bpy.ops.rs_elastic.simulate, bpy.ops.rs_elastic.solve_spacetime):
        assert refusal(operator) == message
    assert user_fingerprint() == before
    assert refusal(bpy.ops.rs_elastic.prepare) == "Stiffness group 'Stiff' does not exist on 'Bar'"

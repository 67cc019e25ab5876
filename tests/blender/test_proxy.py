"""Dense surfaces are tetrahedralised through a simplified proxy (issue 14 item 1).

Oracles: a 65k-triangle UV sphere (radius 1) at edge 0.1 meshes a proxy of at most the budget
(``solver.proxy``, 1,500 triangles here), so its tet mesh is coarse and fast, yet its volume is
the sphere's within 2 %; the panel's estimate names the same counts; the proxy budget is part
of the tet mesh's key (changing it makes a new tet mesh, nothing else is recomputed).
"""
import numpy as np
import bpy

from blender_helpers import make_active


def test_a_dense_sphere_prepares_through_its_proxy(ext):
    bpy.ops.mesh.primitive_uv_sphere_add(segments=256, ring_count=128, radius=1.0)
    obj = bpy.context.active_object
    make_active(obj)
    settings = obj.rs_elastic
    settings.edge_length = 0.1
    triangles, meshed = ext.bridge.estimates.mesh_estimate(obj, settings)
    assert triangles > 60000 and meshed == ext.solver.proxy.MIN_BUDGET
    assert bpy.ops.rs_elastic.tetrahedralize() == {'FINISHED'}
    inputs = ext.bridge.bodies.read_inputs(obj, bpy.context.evaluated_depsgraph_get(),
                                           with_material=False)
    tet_body = ext.bridge.bodies.tet_stage(inputs, ext.bridge.jobs.Job(None))
    volume = np.abs(ext.solver.fem.tet_volumes(tet_body.nodes, tet_body.tets)).sum()
    print(f"{triangles} triangles -> proxy {meshed}; {settings.tet_count} tets, volume "
          f"{volume:.4f} (sphere {4 / 3 * np.pi:.4f})")
    assert abs(volume / (4.0 / 3.0 * np.pi) - 1.0) < 0.02
    assert settings.tet_count < 20000
    key = settings.tets_key
    settings.proxy_triangles = 4000
    assert ext.bridge.bodies.read_inputs(obj, bpy.context.evaluated_depsgraph_get(),
                                         with_material=False).tets_key != key

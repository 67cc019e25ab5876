"""Mode preview: live, never writes the base mesh, and leaves no trace when turned off."""
import numpy as np
import bpy

from blender_helpers import diagonal, evaluated_vertices, fingerprint, make_bar, vertices


def prepared_bar():
    obj = make_bar()
    obj.rs_elastic.edge_length = 0.08
    obj.rs_elastic.num_modes = 4
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    return obj


def test_preview_shows_the_scaled_mode_and_leaves_no_trace(ext):
    obj = prepared_bar()
    rest = vertices(obj)
    before = fingerprint(obj)
    settings = obj.rs_elastic
    settings.preview_method = 'LINEAR'
    settings.preview_mode = 2
    settings.preview_amplitude = 0.2
    settings.preview_enabled = True
    body = ext.bridge.bodies.load_prepared(obj)
    u = body.surface_mode(1)
    expected = rest + u * (0.2 * diagonal(rest) / np.linalg.norm(u, axis=1).max())
    np.testing.assert_allclose(evaluated_vertices(obj), expected, atol=1e-5)
    np.testing.assert_array_equal(vertices(obj), rest)          # base mesh untouched
    settings.preview_amplitude = -0.1                            # live: follows the slider
    shown = evaluated_vertices(obj)
    np.testing.assert_allclose(shown - rest, -(expected - rest) / 2, atol=1e-5)
    settings.preview_enabled = False
    assert obj.data.shape_keys is None
    assert fingerprint(obj) == before


def test_preview_keeps_the_users_shape_keys(ext):
    obj = prepared_bar()
    obj.shape_key_add(name="Basis")
    smile = obj.shape_key_add(name="Smile")
    smile.data[0].co.z += 0.3
    smile.value = 0.5
    before = fingerprint(obj)
    obj.rs_elastic.preview_enabled = True
    assert [k.name for k in obj.data.shape_keys.key_blocks] == ["Basis", "Smile",
                                                                ext.bridge.preview.PREVIEW_KEY]
    obj.rs_elastic.preview_enabled = False
    assert fingerprint(obj) == before


def test_preview_without_preparation_changes_nothing(ext):
    obj = make_bar()
    before = fingerprint(obj)
    obj.rs_elastic.preview_enabled = True
    assert obj.data.shape_keys is None
    obj.rs_elastic.preview_enabled = False
    assert fingerprint(obj) == before

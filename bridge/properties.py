"""Per-object settings and results, saved in the .blend (`obj.rs_elastic`)."""
import bpy
from bpy.props import (BoolProperty, CollectionProperty, EnumProperty, FloatProperty,
                       IntProperty, PointerProperty, StringProperty)

from ..solver import tetmesh

# A setting's change can set off work above the data schema (the mode preview, Live, the tet
# overlay). Those modules hand their reactions in at register time (bridge/handlers.py), so the
# schema imports nothing of the bridge.
_REACTIONS = {}   # reaction name -> function(settings, context)

LAST_FRAME = 1048574   # Blender's last frame; frames may be negative, down to -LAST_FRAME


def set_reaction(name, function):
    """Call ``function(settings, context)`` when a setting with the reaction ``name`` changes."""
    _REACTIONS[name] = function


def _reaction(name):
    def update(self, context):
        function = _REACTIONS.get(name)
        if function is not None:
            function(self, context)
    return update


_preview_changed = _reaction("preview")
_live_changed = _reaction("live")
_show_tets_changed = _reaction("show_tets")


def _is_mesh(_settings, obj):
    return obj.type == 'MESH'


class RSElasticMode(bpy.types.PropertyGroup):
    """One linear mode's result, for the panel and for scripts."""
    frequency_hz: FloatProperty(name="Frequency", unit='NONE', description="Natural frequency in Hz")


def _is_empty(self, obj):
    return obj.type == 'EMPTY'


class RSElasticHandle(bpy.types.PropertyGroup):
    """An Empty bound to a set of the body's vertices (a vertex group)."""
    empty: PointerProperty(type=bpy.types.Object, poll=_is_empty, name="Empty",
                           description="The Empty whose keyed locations the handle must reach")
    vertex_group: StringProperty(name="Vertex Group",
                                 description="The vertices whose centroid follows the Empty")
    follow: BoolProperty(name="Follow Every Frame", default=False,
                         description="Constrain every frame of the range, not only the keyed ones")
    orientation: BoolProperty(name="Orientation", default=False,
                              description="Follow the Empty's rotation too (turns since the first "
                                          "frame of the range, winding included: a 360° key "
                                          "twists the vertices a full turn)")
    weight: FloatProperty(name="Weight", default=1.0, min=0.0, soft_max=10.0,
                          description="How strongly this handle pulls, relative to the others")
    residual: FloatProperty(name="Residual", default=-1.0, subtype='DISTANCE',
                            description="Largest distance from the Empty over the constrained "
                                        "frames after the last solve (-1: not solved)")


class RSElasticValue(bpy.types.PropertyGroup):
    value: FloatProperty()


class RSElasticSettings(bpy.types.PropertyGroup):
    # --- Tetrahedralisation (fTetWild) -------------------------------------------------------------
    edge_length: FloatProperty(
        name="Edge Length", default=0.05, min=0.005, max=0.5, precision=3,
        description="Target tet edge length, as a fraction of the bounding-box diagonal. "
                    "Smaller is finer and slower")
    proxy_triangles: IntProperty(
        name="Proxy Triangles", default=0, min=0, soft_max=200000,
        description="A denser surface is simplified to this many triangles before fTetWild "
                    "meshes it (the render mesh is embedded in the tets anyway); 0: automatic, "
                    "from the edge length")
    envelope: FloatProperty(
        name="Envelope", default=1e-3, min=1e-5, max=0.1, precision=4,
        description="How far the tet surface may stray from the mesh, as a fraction of the "
                    "bounding-box diagonal")
    mesher_time_limit: FloatProperty(
        name="Time Limit", default=tetmesh.DEFAULT_TIME_LIMIT, min=1.0, soft_max=3600.0,
        precision=0, unit='TIME_ABSOLUTE',
        description="Seconds fTetWild may run before it is stopped (the panel shows its "
                    "estimate). A coarser Edge Length, fewer Proxy Triangles or a larger Envelope "
                    "mesh faster")
    show_tets: BoolProperty(
        name="Show Tets", default=False, update=_show_tets_changed,
        description="Draw the tet mesh's edges in the viewport (an overlay; the mesh is not changed)")

    # --- Material (no hard limits, so bad values reach the operators and get a clear message) ------
    youngs_modulus: FloatProperty(
        name="Young's Modulus", default=1.0e6, soft_min=1.0, soft_max=1e11, precision=0,
        description="Stiffness in pascals (Pa)")
    poisson_ratio: FloatProperty(
        name="Poisson's Ratio", default=0.45, soft_min=-0.99, soft_max=0.499, precision=3,
        description="Lateral contraction; must lie strictly between -1 and 0.5")
    density: FloatProperty(
        name="Density", default=1100.0, soft_min=1.0, soft_max=20000.0, precision=1,
        description="Mass density in kg/m³ (Blender units are metres)")
    stiffness_group: StringProperty(
        name="Stiffness Group",
        description="Vertex group that paints the stiffness: weight 1 has the Young's modulus "
                    "above, weight 0 (and every vertex outside the group) Stiffness Ratio times "
                    "it, in between geometrically. Paint the stiff part (or use a ratio above 1 "
                    "to make the painted part the soft one); empty for a uniform material")
    stiffness_ratio: FloatProperty(
        name="Stiffness Ratio", default=0.1, soft_min=1e-4, soft_max=10.0, precision=4,
        description="Young's modulus at weight 0 of the Stiffness Group over that at weight 1 "
                    "(must be above 0; 1: uniform)")
    pin_group: StringProperty(
        name="Pin Group",
        description="Vertex group whose vertices are held fixed; empty for a free body")
    num_modes: IntProperty(
        name="Modes", default=20, min=1, soft_max=100,
        description="Number of linear deformation modes to compute")

    # --- Reduced RS (basis and cubature) ------------------------------------------------------------
    basis_size: IntProperty(
        name="Basis Size", default=0, min=0, soft_max=300,
        description="Largest reduced basis: the modes plus their higher-order RS terms "
                    "(0: automatic, growing with the modes: 120 at 10 modes, 230 at 20, 860 at 40, "
                    "within memory and the tet count)")
    cubature_tets: IntProperty(
        name="Cubature Tets", default=150, min=1, soft_max=1000,
        description="Largest number of tets the reduced RS map is evaluated on")
    cubature_tolerance: FloatProperty(
        name="Cubature Tolerance", default=2e-3, min=1e-6, max=0.5, precision=4,
        description="Relative fit error at which cubature training stops")
    training_poses: IntProperty(
        name="Training Poses", default=80, min=4, soft_max=400,
        description="Random large-rotation poses the cubature is trained on")

    # --- Simulation ---------------------------------------------------------------------------------
    material_model: EnumProperty(
        name="Material Model", default='LINEAR',
        items=[('LINEAR', "Linear", "Linear elasticity on the rotation-free (Cauchy) strain"),
               ('STVK', "StVK", "St. Venant-Kirchhoff on the Cauchy strain: stiffer when "
                                "strongly stretched"),
               ('FUNG', "Fung", "Exponential stiffening, like soft tissue")],
        description="How the body resists strain in the simulation")
    fung_stiffening: FloatProperty(
        name="Stiffening", default=10.0, min=0.1, soft_max=100.0,
        description="Fung stiffening: how soon the Fung material stiffens: around a strain of 1/sqrt(this)")
    integrator: EnumProperty(
        name="Integrator", default='NEWMARK',
        items=[('NEWMARK', "Newmark", "Average acceleration (trapezoidal rule): keeps the energy, "
                                      "so only the damping you set slows the motion"),
               ('IMPLICIT_EULER', "Implicit Euler", "Damps the motion numerically, more at "
                                                    "low frame rates and few substeps")],
        description="Time integration of the simulation")
    substeps: IntProperty(
        name="Substeps", default=0, min=0, max=1000, soft_max=64,
        description="Steps per frame; 0 = automatic, from the body's highest mode frequency, "
                    "so the motion does not depend on the frame rate")
    start_settled: BoolProperty(
        name="Start Settled", default=False,
        description="Start at rest in static equilibrium under gravity (on a rig, also under "
                    "its first frame's loads) instead of from the undeformed shape, so a pinned "
                    "body does not sag and bounce over the first frames")

    use_collisions: BoolProperty(
        name="Collisions", default=True,
        description="Collide with objects that have a Collision modifier (its Thickness Outer, "
                    "Friction and Damping apply)")
    collider_collection: PointerProperty(
        type=bpy.types.Collection, name="Colliders",
        description="Only collide with the colliders in this collection (empty: every collider "
                    "in the scene)")
    contact_samples: IntProperty(
        name="Samples", default=256, min=8, max=4096, soft_max=1024,
        description="Contact samples: surface points that feel the colliders; more catch smaller features and cost "
                    "more per step")

    # --- Results, written by the operators -----------------------------------------------------------
    tet_node_count: IntProperty(name="Nodes", default=0)
    tet_count: IntProperty(name="Tets", default=0)
    tets_key: StringProperty(name="Tet Mesh Key", default="",
                             description="Cache key of the tet mesh this object was tetrahedralised to")
    prepared_key: StringProperty(name="Prepared Key", default="",
                                 description="Cache key of the modes this object was prepared with")
    reduced_key: StringProperty(name="Reduced Key", default="",
                                description="Cache key of the reduced RS deformer")
    reduced_basis_count: IntProperty(name="Basis", default=0)
    cubature_count: IntProperty(name="Cubature", default=0)
    mode_results: CollectionProperty(type=RSElasticMode)
    mnf: FloatProperty(name="MNF", default=0.0,
                       description="Minimal natural frequency sqrt(lambda_1) in rad/s: lower means a "
                                   "softer, more nonlinear body")

    # --- Mode preview ---------------------------------------------------------------------------------
    preview_enabled: BoolProperty(
        name="Preview Mode", default=False, update=_preview_changed,
        description="Show the body displaced along one mode (a temporary shape key, removed when off)")
    preview_method: EnumProperty(
        name="Method", update=_preview_changed,
        items=[('LINEAR', "Linear", "Rest pose plus the scaled mode: stretches at large amplitude"),
               ('RS', "RS", "The mode warped through rotation-strain coordinates: bends and "
                            "curls without inflating"),
               ('REDUCED', "Reduced RS", "RS through the reduced basis and its cubature: the "
                                         "same motion at a cost independent of mesh size")],
        default='RS',
        description="How the mode is turned into a pose")
    preview_mode: IntProperty(name="Mode", default=1, min=1, update=_preview_changed,
                              description="Which mode to show (1 = lowest frequency)")
    preview_amplitude: FloatProperty(
        name="Amplitude", default=0.1, soft_min=-1.0, soft_max=1.0, precision=3,
        update=_preview_changed,
        description="Largest displacement of the mode, as a fraction of the bounding-box diagonal")

    # --- Space-time editing ---------------------------------------------------------------------------
    handles: CollectionProperty(type=RSElasticHandle)
    active_handle: IntProperty(default=0)
    use_scene_range: BoolProperty(name="Scene Range", default=True,
                                  description="Solve over the scene's frame range")
    frame_start: IntProperty(name="Start", default=1, min=-LAST_FRAME, max=LAST_FRAME)
    frame_end: IntProperty(name="End", default=100, min=-LAST_FRAME, max=LAST_FRAME)
    optimize_material: BoolProperty(
        name="Optimize Material", default=False,
        description="Also optimise frequencies, damping and mode shapes so the motion stays "
                    "physically consistent (slower)")
    material_freedom: FloatProperty(
        name="Material Freedom", default=1.5, min=1.0, soft_max=4.0, precision=2,
        description="How much Optimize Material may change the body: every mode's frequency and "
                    "damping stays within this factor of the prepared body's (1 keeps them, 2 "
                    "allows half to double); within it, changes are still resisted")
    tightness: FloatProperty(
        name="Tightness", default=1e4, min=1.0, soft_max=1e8,
        description="How tightly handles and pose keys are met against the control force: a "
                    "constraint misses by about its unconstrained miss divided by this")
    damping_mass: FloatProperty(
        name="Mass Damping", default=0.1, min=0.0, soft_max=10.0,
        description="Rayleigh damping α (1/s): slows every mode alike")
    damping_stiffness: FloatProperty(
        name="Stiffness Damping", default=0.002, min=0.0, soft_max=0.1, precision=4,
        description="Rayleigh damping β (s): damps fast modes more than slow ones")
    live: BoolProperty(
        name="Live", default=False, update=_live_changed,
        description="Re-solve whenever a handle's Empty or its keyframes change and show the "
                    "pose at the current frame as the preview (never the bake; Solve and Bake "
                    "writes that)")
    iterations: IntProperty(
        name="Iterations", default=0, min=0, soft_max=200,
        description="Largest number of solver iterations: Gauss-Newton steps of the motion, or "
                    "rounds with Optimize Material; 0 = automatic (until converged, up to 200 "
                    "steps, 50 where handles are keyed on many frames, or 20 rounds)")
    bake_to: EnumProperty(
        name="Bake To", default='KEYS',
        items=[('KEYS', "Shape Keys", "One shape key per frame, inside the .blend (short shots)"),
               ('CACHE', "Mesh Cache", "A .pc2 file next to the saved .blend, played by a Mesh "
                                       "Cache modifier (long shots, dense meshes)")],
        description="Where a bake goes")
    cache_bake_file: StringProperty(
        name="Cache Bake File", default="",
        description="The .pc2 file of the current Mesh Cache bake (written by the extension). "
                    "Its name holds the bake's identity: the extension's modifier is the Mesh "
                    "Cache modifier playing a file of that name")
    use_take: BoolProperty(name="Edit the Take", default=False,
                           description="Use the stored take (a kept bake) as the input motion")
    take_weight: FloatProperty(name="Take Weight", default=0.01, min=0.0, soft_max=1.0,
                               precision=4,
                               description="How closely the edit follows the input take, "
                                           "relative to a handle: keep it small, so edits can "
                                           "bend the take around them")
    solve_history: CollectionProperty(type=RSElasticValue)
    take_source: PointerProperty(
        type=bpy.types.Object, poll=_is_mesh, name="Take Source",
        description="The object whose evaluated motion Take from Animation reads (same "
                    "vertices, same order); empty: this object itself")
    fit_frame_start: IntProperty(name="Fit Start", default=0, min=-LAST_FRAME, max=LAST_FRAME,
                                 description="First take frame Fit Material fits (with Fit End "
                                             "0 or below Fit Start: the whole take)")
    fit_frame_end: IntProperty(name="Fit End", default=0, min=-LAST_FRAME, max=LAST_FRAME,
                               description="Last take frame Fit Material fits")
    use_fitted_material: BoolProperty(
        name="Use Fitted Material", default=False,
        description="The space-time editor uses the material Fit Material recovered from the "
                    "take (each mode's frequency and damping) instead of the prepared one")

    @property
    def frequencies(self):
        """Natural frequencies in Hz, ascending (empty until prepared)."""
        return tuple(item.frequency_hz for item in self.mode_results)

    @property
    def is_prepared(self):
        return bool(self.prepared_key)


CLASSES = (RSElasticMode, RSElasticHandle, RSElasticValue, RSElasticSettings)


def register():
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.Object.rs_elastic = bpy.props.PointerProperty(type=RSElasticSettings)


def unregister():
    del bpy.types.Object.rs_elastic
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)

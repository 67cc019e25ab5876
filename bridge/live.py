"""Live re-solve of a space-time edit: the preview follows the handles while they are edited.

With a body's Live setting on, moving one of its handles' Empties or changing their keyframes
re-solves the edit, warm-started from the last live solution of the same preparation, and shows
the pose at the current frame as the preview shape key (bridge/preview.py's key, owned by the
extension). Live never writes the bake: only Solve and Bake does, so no edit made live can
replace work. Outside Object Mode it writes nothing (as the mode preview); the pose shows once the
body is back in Object Mode.

Flow (main thread unless said): ``on_depsgraph_update`` notes which bodies' handles changed; a
``bpy.app.timers`` callback (``_tick``) gathers the problem (bpy), runs ``_solve`` on a worker
thread (pure numpy), waits up to ``FOLLOW`` seconds for it and shows the result, or shows it on a
later tick. One re-solve per body runs at a time; the changes made meanwhile (a drag's many
mouse moves) make one re-solve after it, so the preview follows a drag about one redraw behind.
In background mode timers do not run: ``flush`` does the same synchronously (what tests and
scripts call).

Gathering never sets the scene's frame for a handle that only its own keys move
(``transforms.curve_world_matrices``): frame_set would put the Empty the artist is dragging back
on its key. A handle placed otherwise (a parent that moves, a constraint) waits for the move to
end (``transforms.ArtistMoving``).

Coarser than Solve and Bake, to keep up with the mouse: a warm re-solve runs at most
``LIVE_GN_STEPS`` Gauss-Newton steps, no penalty continuation, and no material optimisation (the
prepared material is used even if Optimize Material is on). The first live solve of a body is a
full Z solve (with continuation) since there is nothing to warm-start from.
"""
import dataclasses
import threading
import time

import numpy as np

from ..solver import spacetime, threads
from . import bake, preview, scene, spacetime_inputs, transforms
from .scene import InputError

POLL = 0.02           # s between timer ticks while something is pending or running
FOLLOW = 0.03         # s a tick waits for the re-solve it started (a warm one takes ~5-40 ms),
#                       so its pose shows on the next redraw rather than a timer tick later
LIVE_GN_STEPS = 3     # GN steps of a warm re-solve (a small handle move converges in 1-2)


@dataclasses.dataclass
class LiveSolution:
    frames: list          # scene frames, ascending
    Z: np.ndarray         # (F, r) modal inputs, the next re-solve's warm start
    inputs: np.ndarray    # (F, m) deformer inputs S z per frame
    body: object          # the solver.body.PreparedBody the solve used
    rest: np.ndarray      # (n, 3) base vertices [object units]
    status: str           # one line for the panel

    def pose(self, index):
        """(n, 3) base-vertex positions of frame ``frames[index]``: only the shown frame is
        reconstructed, which is most of a re-solve's cost when done for every frame."""
        return self.body.surface_positions(self.rest, self.inputs[index])


SOLUTIONS = {}        # object name -> LiveSolution (session only, like the solve status)
ERRORS = {}           # object name -> why the last live solve could not run
_PENDING = {}         # object name -> time.monotonic() of the last change
_RUNNING = {}         # object name -> (thread, box: dict filled by the worker)
_TIMER_ON = [False]


# ---------------------------------------------------------------------------------------------
# The solve (worker thread: no bpy)

def _solve(job):
    """(Z, inputs, status) for a gathered ``SpaceTimeJob``, warm-started if a fitting Z exists."""
    previous = SOLUTIONS.get(job.object_name)
    shape = (job.problem.frames, job.problem.num_modes)
    # Only the same preparation's Z: another one's modal coordinates mean another motion
    # (scaled by another density, or other modes).
    warm = (previous is not None and previous.body is job.body and previous.Z.shape == shape
            and previous.frames == job.frames)
    with threads.one_blas_thread():             # as every job's work (``jobs``)
        if warm:
            result = spacetime.solve(job.problem, iterations=LIVE_GN_STEPS, initial=previous.Z,
                                     continuation=False)
        else:
            result = spacetime.solve(job.problem, iterations=job.iterations)
    how = "warm" if warm else "cold"
    status = (f"Live: {how} re-solve, {result.iterations} steps, largest handle miss "
              f"{float(result.handle_residuals.max(initial=0.0)):.2g}")
    return result.Z, result.inputs, status


# ---------------------------------------------------------------------------------------------
# Showing a solution (main thread)

def show(obj, blender_scene):
    """Put the live pose of the current frame on the preview key (hide it outside the range)."""
    solution = SOLUTIONS.get(obj.name)
    frame = blender_scene.frame_current
    if solution is None or not solution.frames[0] <= frame <= solution.frames[-1]:
        preview.hide(obj)
        return False
    scene.require_single_user(obj)
    if not preview.in_object_mode(obj):     # shown once back in Object Mode (handlers.py)
        return False
    pose = solution.pose(frame - solution.frames[0])
    if not np.all(np.isfinite(pose)):       # a diverged re-solve must not reach the mesh
        ERRORS[obj.name] = "Live: the re-solve diverged; move the handle back or run Solve and Bake"
        preview.hide(obj)
        return False
    # Shape keys add: a bake key at 1 on this frame would add its own displacement on top of
    # the preview's, so the preview carries the difference to the bake (the bake is not touched).
    baked = {f: b for f, b in bake._frames_and_blocks(obj, "bake", bake.BAKE_PREFIX)}
    if frame in baked:
        block = baked[frame]
        co = np.empty(len(block.data) * 3, dtype=np.float32)
        block.data.foreach_get("co", co)
        pose = pose + (scene.base_vertices(obj) - co.reshape(-1, 3))
    preview.write_key(obj, pose)
    return True


def stop(obj):
    """Live turned off: forget its solution and give the preview key back to Preview Mode
    (removed unless Preview Mode is on), so the mesh is as it was before Live."""
    for table in (SOLUTIONS, ERRORS, _PENDING):
        table.pop(obj.name, None)
    preview.refresh(obj)


def _store(obj, blender_scene, job, Z, inputs, status):
    SOLUTIONS[obj.name] = LiveSolution(list(job.frames), Z, inputs, job.body, job.rest, status)
    ERRORS.pop(obj.name, None)
    show(obj, blender_scene)


def status(obj):
    """One line for the panel, or None."""
    if obj.name in ERRORS:
        return ERRORS[obj.name]
    if obj.name in _RUNNING or obj.name in _PENDING:
        return "Live: re-solving…"
    solution = SOLUTIONS.get(obj.name)
    return None if solution is None else solution.status


# ---------------------------------------------------------------------------------------------
# Noticing changes

def _live_bodies(blender_scene):
    return [o for o in blender_scene.objects
            if o.type == 'MESH' and getattr(o.rs_elastic, "live", False)]


def _watched(obj):
    """Names of the Empties and Actions whose change invalidates obj's live solution."""
    objects, actions = set(), set()
    for handle in obj.rs_elastic.handles:
        empty = handle.empty
        if empty is None:
            continue
        objects.add(empty.name)
        if empty.animation_data is not None and empty.animation_data.action is not None:
            actions.add(empty.animation_data.action.name)
    return objects, actions


def changed_bodies(blender_scene, updates):
    """Names of live bodies whose handle Empties moved or whose handles' actions changed."""
    moved, edited = set(), set()
    for update in updates:
        block = update.id
        if block is None:
            continue
        kind = type(block).__name__
        if kind == 'Object' and update.is_updated_transform:
            moved.add(block.name)
        elif kind == 'Action':
            edited.add(block.name)
    if not moved and not edited:
        return []
    names = []
    for obj in _live_bodies(blender_scene):
        objects, actions = _watched(obj)
        if objects & moved or actions & edited:
            names.append(obj.name)
    return names


def on_depsgraph_update(blender_scene, depsgraph):
    """depsgraph_update_post: mark bodies to re-solve, and start the timer that runs them."""
    names = changed_bodies(blender_scene, depsgraph.updates)
    for name in names:
        request(name)


def request(name):
    """Ask for a re-solve of body `name` (on the next timer tick, or after the running one)."""
    _PENDING[name] = time.monotonic()
    if not _TIMER_ON[0] and not _background():
        import bpy
        _TIMER_ON[0] = True
        bpy.app.timers.register(_tick, first_interval=0.0)


def _background():
    import bpy
    return bpy.app.background


def on_frame_change(blender_scene, *_args):
    """frame_change_post: show the stored live pose of the new frame (no solve)."""
    for obj in _live_bodies(blender_scene):
        if obj.name in SOLUTIONS:
            try:
                show(obj, blender_scene)
            except InputError:
                pass


# ---------------------------------------------------------------------------------------------
# Running re-solves

def _objects():
    import bpy
    return bpy.data.objects, bpy.context.scene


def _start(name, synchronous):
    objects, blender_scene = _objects()
    obj = objects.get(name)
    if obj is None or not obj.rs_elastic.live:
        return
    if not preview.in_object_mode(obj):      # solved once back in Object Mode (handlers.py)
        return
    try:
        job = spacetime_inputs.gather(obj, blender_scene)
    except transforms.ArtistMoving:     # a handle only the scene can place: once the move ends
        _PENDING[name] = time.monotonic()
        return
    except InputError as error:
        ERRORS[name] = f"Live: {error}"
        return
    if synchronous:
        _store(obj, blender_scene, job, *_solve(job))
        return
    box = {}

    def work():
        try:
            box["output"] = _solve(job)
        except Exception as error:      # shown in the panel; the worker must not die silently
            box["error"] = f"Live: {error}"
    thread = threading.Thread(target=work, name=f"rs-elastic-live-{name}", daemon=True)
    _RUNNING[name] = (thread, box, job)
    thread.start()


def _finish(name, box, job):
    objects, blender_scene = _objects()
    obj = objects.get(name)
    if obj is None or not obj.rs_elastic.live:
        return
    if "error" in box:
        ERRORS[name] = box["error"]
        return
    try:
        _store(obj, blender_scene, job, *box["output"])
    except InputError as error:
        ERRORS[name] = f"Live: {error}"


def _collect_finished():
    for name, (thread, box, job) in list(_RUNNING.items()):
        if not thread.is_alive():
            del _RUNNING[name]
            _finish(name, box, job)


def _tick():
    """Timer: collect finished workers, start pending re-solves (one per body at a time), wait
    briefly for them; keeps running while busy."""
    _collect_finished()
    for name in [n for n in _PENDING if n not in _RUNNING]:
        del _PENDING[name]
        _start(name, synchronous=False)
    deadline = time.monotonic() + FOLLOW
    for thread, _, _ in list(_RUNNING.values()):
        thread.join(max(0.0, deadline - time.monotonic()))
    _collect_finished()
    if _RUNNING or _PENDING:
        return POLL
    _TIMER_ON[0] = False
    return None


def flush():
    """Run every pending re-solve now, synchronously (background mode has no timers).
    Returns the names re-solved."""
    names = list(_PENDING)
    _PENDING.clear()
    for name in names:
        _start(name, synchronous=True)
    return names


def cancel():
    """Extension unloading: stop the timer and forget queued re-solves (a running worker
    finishes on its own; its result is dropped)."""
    import bpy
    if bpy.app.timers.is_registered(_tick):
        bpy.app.timers.unregister(_tick)
    _TIMER_ON[0] = False
    _PENDING.clear()
    _RUNNING.clear()

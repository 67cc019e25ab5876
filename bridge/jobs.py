"""Long operators: one piece of work, run either on a worker thread (UI, modal, Esc cancels) or
synchronously (scripts and background mode, where modal operators and timers never run).

The work is a plain function `work(job)` that must not touch bpy: it reads arrays prepared on the
main thread, calls `job.step(fraction, message)` between stages (which raises `Cancelled` once Esc
was pressed; an optional `note` says something about the run while it lasts, such as why it is
slow), and returns a result that the operator applies to Blender on the main thread.

Reading the scene can itself take long (a take read frame by frame). Such an operator's
`make_work` is a generator: it yields (fraction, message) between pieces of main-thread reading
and returns `work`. In the UI its pieces run on the timer's ticks, `READ_BUDGET` seconds at a
time, so the window stays responsive, shows the progress and hears Esc, which closes the
generator (its `finally` puts the scene back); in background mode it runs to its end at once.

While a work runs, numpy's BLAS runs on one thread (`solver.threads.one_blas_thread`): the
solver's work is its own threads or many small products, which BLAS threads slow down.
"""
import inspect
import threading
import time

import bpy

from ..solver import threads

POLL = 0.1              # s between the modal operator's timer ticks while a job runs
CANCEL_POLL = 0.01      # s between ticks once Esc was pressed: the operator ends right after the work
READ_POLL = 0.01        # s between ticks while a generator reads the scene on the main thread
READ_BUDGET = 0.05      # s of that reading per tick (the window handles its events in between)
RUNNING = {}            # {object name: Job} of the modal jobs running now (the panels' progress bars)
# What a running job lets through to the window: looking around (orbit, pan and zoom a view,
# scroll the sidebar) changes none of the user's data. Every other event (clicks, keys, and the
# wheel with Ctrl or Alt, which change values and frames) waits for the job's end.
NAVIGATION_EVENTS = frozenset({'MOUSEMOVE', 'INBETWEEN_MOUSEMOVE', 'MIDDLEMOUSE', 'WHEELUPMOUSE',
                               'WHEELDOWNMOUSE', 'TRACKPADPAN', 'TRACKPADZOOM', 'MOUSEROTATE',
                               'MOUSESMARTZOOM', 'NDOF_MOTION'})


class Cancelled(Exception):
    """The user pressed Esc; nothing was applied."""


class Job:
    """A piece of work (`work(job)`), or a generator reading the scene on the main thread that
    yields (fraction, message) and returns the work (module docstring)."""

    def __init__(self, work, idname="", object_name=""):
        self.reader = work if inspect.isgenerator(work) else None
        self._work = None if self.reader is not None else work
        self.idname, self.object_name = idname, object_name
        self._cancel = threading.Event()
        self._thread = None
        self.fraction = 0.0
        self.message = "Starting"
        self.note = None        # a sentence on the run so far, or None (panels draw it wrapped)
        self.warnings = []
        self.result = None
        self.error = None

    # --- called by the work --------------------------------------------------------------------------
    def step(self, fraction, message, note=None):
        if self._cancel.is_set():
            raise Cancelled()
        self.fraction, self.message, self.note = float(fraction), message, note

    def warn(self, message):
        self.warnings.append(message)

    def is_cancelled(self):
        """Asked by the work between its small steps (a substep, an iteration). It also hands
        Python's lock to the main thread if that waits for it (sleep(0) releases it): otherwise
        each of the main thread's Python calls (a panel's draw, the modal handler that hears
        Esc) may wait up to the interpreter's switch interval (5 ms) for it."""
        time.sleep(0)
        return self._cancel.is_set()

    # --- called by the operator ----------------------------------------------------------------------
    def read(self, seconds=None):
        """Main thread: advance the reader for about `seconds` (None: to its end); True once it
        has returned the work. Its exceptions propagate."""
        end = None if seconds is None else time.monotonic() + seconds
        try:
            while True:
                self.fraction, self.message = next(self.reader)
                if end is not None and time.monotonic() >= end:
                    return False
        except StopIteration as stop:
            self._work, self.reader = stop.value, None
            return True

    def run_here(self):
        """Run synchronously (the reading too); exceptions propagate."""
        if self.reader is not None:
            self.read()
        self.result = self._run_work()
        return self.result

    def _run_work(self):
        """The work's result, with numpy's BLAS on one thread while it runs (module docstring)."""
        with threads.one_blas_thread():
            return self._work(self)

    def start(self):
        self._thread = threading.Thread(target=self._run_caught, daemon=True)
        self._thread.start()

    def _run_caught(self):
        try:
            self.result = self._run_work()
        except BaseException as exc:  # handed to the main thread, which reports it
            self.error = exc

    def cancel(self):
        """Stop the work at its next check; a reading stops now, its generator closed (main
        thread)."""
        self._cancel.set()
        if self.reader is not None:
            self.reader.close()

    @property
    def done(self):
        return self._thread is not None and not self._thread.is_alive()


def looks_around(event):
    """True for an event that only moves a view (``NAVIGATION_EVENTS`` without Ctrl, Alt or the
    OS key)."""
    return event.type in NAVIGATION_EVENTS and not (event.ctrl or event.alt or event.oskey)


def running_job(obj):
    """The modal job running on `obj` now (its operator's `idname`, `fraction` and `message`),
    or None."""
    return RUNNING.get(obj.name) if obj is not None else None


def python_idname(idname):
    """"rs_elastic.prepare" for either spelling (an operator instance says "RS_ELASTIC_OT_prepare")."""
    if "_OT_" in idname:
        module, name = idname.split("_OT_", 1)
        return f"{module.lower()}.{name}"
    return idname


PANEL_REGIONS = {('VIEW_3D', 'UI'), ('PROPERTIES', 'WINDOW')}


def _redraw_sidebars(context):
    """Redraw the regions where the panels draw the progress bar (the 3D viewports' sidebars and
    the Properties editors), not the viewports: with software OpenGL a viewport's redraw takes
    long enough to hold back Esc."""
    screen = context.window.screen if context.window is not None else None
    for area in screen.areas if screen is not None else ():
        for region in area.regions:
            if (area.type, region.type) in PANEL_REGIONS:
                region.tag_redraw()


class JobOperator:
    """Mixin for an operator whose work may take long.

    Subclasses implement `make_work(context)` (main thread: read and validate the scene, raise
    `InputError` for bad input, return `work(job)`; or a generator that reads step by step, see
    the module docstring), and `apply(context, result, job)` (main thread: write the result into
    Blender, return the operator's return set).
    """

    _job = None
    _timer = None

    def make_work(self, context):
        raise NotImplementedError

    def apply(self, context, result, job):
        raise NotImplementedError

    def _start(self, context):
        from .scene import InputError, acted_on
        obj = acted_on(context)
        try:
            return Job(self.make_work(context), python_idname(self.bl_idname),
                       obj.name if obj else "")
        except InputError as exc:
            self.report({'ERROR'}, str(exc))
            return None

    def _finish(self, context, job):
        for message in job.warnings:
            self.report({'WARNING'}, message)
        return self.apply(context, job.result, job)

    def _fail(self, exc):
        from .scene import InputError
        if isinstance(exc, Cancelled):
            self.report({'WARNING'}, f"{self.bl_label}: cancelled, nothing was changed")
        elif isinstance(exc, (InputError, RuntimeError, ValueError, MemoryError)):
            self.report({'ERROR'}, str(exc))
        else:
            self.report({'ERROR'}, f"{self.bl_label} failed: {type(exc).__name__}: {exc}")
        return {'CANCELLED'}

    def execute(self, context):
        job = self._start(context)
        if job is None:
            return {'CANCELLED'}
        try:
            job.run_here()
        except Exception as exc:
            return self._fail(exc)
        return self._finish(context, job)

    def invoke(self, context, event):
        if bpy.app.background:
            return self.execute(context)
        job = self._start(context)
        if job is None:
            return {'CANCELLED'}
        self._run_modal(context, job)
        context.window_manager.modal_handler_add(self)
        return {'RUNNING_MODAL'}

    def _run_modal(self, context, job):
        """Start `job` (its reading on the timer's ticks, else its thread), with the timer that
        polls it, the cursor's progress and the panels' progress bar (the modal handler is
        added once, by invoke)."""
        self._job = job
        if job.reader is None:
            job.start()
        wm = context.window_manager
        self._set_timer(context, POLL if job.reader is None else READ_POLL)
        wm.progress_begin(0, 100)
        RUNNING[job.object_name] = job

    def _set_timer(self, context, period):
        wm = context.window_manager
        if self._timer is not None:
            wm.event_timer_remove(self._timer)
        self._timer = wm.event_timer_add(period, window=context.window)

    def _cleanup(self, context):
        wm = context.window_manager
        if self._timer is not None:
            wm.event_timer_remove(self._timer)
            self._timer = None
        wm.progress_end()
        if RUNNING.get(self._job.object_name) is self._job:
            del RUNNING[self._job.object_name]
        _redraw_sidebars(context)
        if context.workspace is not None:
            context.workspace.status_text_set(None)

    _shown = None

    def _show_progress(self, context, job):
        """The cursor's progress, the status bar and the panels' bar, redrawn only when what
        they show changed: a redraw runs every panel's Python draw, which waits for the worker
        to hand over Python's lock each time, and would slow the main thread (and Esc) down."""
        shown = (round(100 * job.fraction), job.message, job.note)
        if shown == self._shown:
            return
        before = self._shown or (None, None, None)
        if shown[0] != before[0]:                           # the bar moved
            context.window_manager.progress_update(shown[0])
        if shown[0] != before[0] or shown[2] != before[2]:  # ... or a note came or went
            _redraw_sidebars(context)
        self._shown = shown
        if context.workspace is not None:
            note = f" - {job.note}" if job.note else ""
            context.workspace.status_text_set(
                f"{self.bl_label}: {job.message} ({shown[0]} %){note} - Esc to cancel")

    def modal(self, context, event):
        job = self._job
        if event.type == 'ESC' and event.value == 'PRESS' and not job.is_cancelled():
            job.cancel()            # the work stops at its next check (a substep, a stage)
            self._set_timer(context, CANCEL_POLL)
        if job.reader is not None:          # still reading the scene (closed by a cancel)
            return self._read(context, event, job)
        if event.type != 'TIMER' and not job.done:
            return {'PASS_THROUGH'} if looks_around(event) else {'RUNNING_MODAL'}
        if not job.done:
            self._show_progress(context, job)
            return {'RUNNING_MODAL'}
        self._cleanup(context)
        if job.error is not None:
            return self._fail(job.error)
        if job.is_cancelled():
            return self._fail(Cancelled())
        return self._finish(context, job)

    def _read(self, context, event, job):
        """A tick of the main-thread reading: READ_BUDGET of it, then the work on its thread."""
        if job.is_cancelled():
            self._cleanup(context)
            return self._fail(Cancelled())
        if event.type != 'TIMER':
            return {'PASS_THROUGH'} if looks_around(event) else {'RUNNING_MODAL'}
        try:
            finished = job.read(READ_BUDGET)
        except Exception as exc:
            self._cleanup(context)
            return self._fail(exc)
        if finished:
            job.start()
            self._set_timer(context, POLL)
        self._show_progress(context, job)
        return {'RUNNING_MODAL'}

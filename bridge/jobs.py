"""Long operators: one piece of work, run either on a worker thread (UI, modal, Esc cancels) or
synchronously (scripts and background mode, where modal operators and timers never run).

The work is a plain function `work(job)` that must not touch bpy: it reads arrays prepared on the
main thread, calls `job.step(fraction, message)` between stages (which raises `Cancelled` once Esc
was pressed), and returns a result that the operator applies to Blender on the main thread.
"""
import threading

import bpy


class Cancelled(Exception):
    """The user pressed Esc; nothing was applied."""


class Job:
    def __init__(self, work):
        self._work = work
        self._cancel = threading.Event()
        self._thread = None
        self.fraction = 0.0
        self.message = "Starting"
        self.warnings = []
        self.result = None
        self.error = None

    # --- called by the work --------------------------------------------------------------------------
    def step(self, fraction, message):
        if self._cancel.is_set():
            raise Cancelled()
        self.fraction, self.message = float(fraction), message

    def warn(self, message):
        self.warnings.append(message)

    def is_cancelled(self):
        return self._cancel.is_set()

    # --- called by the operator ----------------------------------------------------------------------
    def run_here(self):
        """Run synchronously; exceptions propagate."""
        self.result = self._work(self)
        return self.result

    def start(self):
        self._thread = threading.Thread(target=self._run_caught, daemon=True)
        self._thread.start()

    def _run_caught(self):
        try:
            self.result = self._work(self)
        except BaseException as exc:  # handed to the main thread, which reports it
            self.error = exc

    def cancel(self):
        self._cancel.set()

    @property
    def done(self):
        return self._thread is not None and not self._thread.is_alive()


class JobOperator:
    """Mixin for an operator whose work may take long.

    Subclasses implement `make_work(context)` (main thread: read and validate the scene, raise
    `InputError` for bad input, return `work(job)`), and `apply(context, result, job)` (main thread:
    write the result into Blender, return the operator's return set).
    """

    _job = None
    _timer = None

    def make_work(self, context):
        raise NotImplementedError

    def apply(self, context, result, job):
        raise NotImplementedError

    def _start(self, context):
        from .scene import InputError
        try:
            return Job(self.make_work(context))
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
        self._job = job
        job.start()
        wm = context.window_manager
        self._timer = wm.event_timer_add(0.1, window=context.window)
        wm.progress_begin(0, 100)
        wm.modal_handler_add(self)
        return {'RUNNING_MODAL'}

    def _cleanup(self, context):
        wm = context.window_manager
        if self._timer is not None:
            wm.event_timer_remove(self._timer)
            self._timer = None
        wm.progress_end()
        if context.workspace is not None:
            context.workspace.status_text_set(None)

    def modal(self, context, event):
        job = self._job
        if event.type == 'ESC' and event.value == 'PRESS':
            job.cancel()
        if event.type != 'TIMER':
            return {'RUNNING_MODAL'}
        if not job.done:
            context.window_manager.progress_update(int(100 * job.fraction))
            if context.workspace is not None:
                context.workspace.status_text_set(
                    f"{self.bl_label}: {job.message} ({100 * job.fraction:.0f} %) - Esc to cancel")
            return {'RUNNING_MODAL'}
        self._cleanup(context)
        if job.error is not None:
            return self._fail(job.error)
        if job.is_cancelled():
            return self._fail(Cancelled())
        return self._finish(context, job)

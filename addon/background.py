"""Long work off Blender's thread: a `Job` runs a core function (no bpy) in a worker thread while a modal
operator polls it from a timer, shows the elapsed time in the status bar, and leaves on Esc with the scene
as it was (the worker's result is dropped). Headless (`bpy.app.background`: no event loop, timers never
fire) the operators run the same job and wait for it."""
from __future__ import annotations

import threading
import time

import bpy


class Cancel:
    """Set by Esc; work that takes it (the boards' deploy) stops at its next step: `requested`, `name`."""

    requested, name = False, "Esc"


class Job:
    """`fn(*args)` in a daemon thread: `done`, then `result` or `error` (the exception it raised). `cancel`:
    the `Cancel` that `fn` was also given, if any, for Esc to set."""

    def __init__(self, fn, *args, cancel: Cancel | None = None):
        self.result, self.error, self.t0, self.cancel = None, None, time.monotonic(), cancel
        self.thread = threading.Thread(target=self._run, args=(fn, args), daemon=True)
        self.thread.start()

    def _run(self, fn, args) -> None:
        try:
            self.result = fn(*args)
        except Exception as e:  # handed to the operator, which reports it
            self.error = e

    @property
    def done(self) -> bool:
        return not self.thread.is_alive()

    def wait(self, timeout: float | None = None) -> bool:
        """Block until done (or `timeout` s); whether it is done."""
        self.thread.join(timeout)
        return self.done

    def elapsed(self) -> float:
        return time.monotonic() - self.t0

    def outcome(self):
        """The result, or the exception `fn` raised, raised here."""
        if self.error is not None:
            raise self.error
        return self.result


class Modal:
    """Mixin for an operator whose `execute` hands long work to `start(context, job, finish)`: a timer polls
    the job; `finish(context, job)` runs in Blender's thread when it is done; Esc cancels."""

    _job = _timer = _finish = None

    def run(self, context, job: Job, what: str, modal: bool = True):
        """`job` with progress and Esc where Blender has an event loop (and `modal`); else waited for here. Either
        way `self.finish(context, job)` ends it."""
        if modal and not bpy.app.background:
            return self.start(context, job, self.finish, what)
        job.wait()
        return self.finish(context, job)

    def start(self, context, job: Job, finish, what: str):
        self._job, self._finish, self._what = job, finish, what
        wm = context.window_manager
        self._timer = wm.event_timer_add(0.1, window=context.window)
        wm.modal_handler_add(self)
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        if event.type == "ESC":
            if self._job.cancel is not None:
                self._job.cancel.requested = True
            self._stop(context)
            self.report({"WARNING"}, f"{self._what}: cancelled; the scene is as it was")
            return {"CANCELLED"}
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        if not self._job.done:
            context.workspace.status_text_set(f"{self._what}: {self._job.elapsed():.0f} s (Esc cancels)")
            return {"RUNNING_MODAL"}
        self._stop(context)
        return self._finish(context, self._job)

    def _stop(self, context) -> None:
        context.window_manager.event_timer_remove(self._timer)
        context.workspace.status_text_set(None)

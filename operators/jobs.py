"""Long operations in Blender: a modal operator that runs core work off the UI thread.

The pattern: ``prepare(context)`` reads everything it needs from ``bpy`` on the main
thread and returns a plain callable ``work(progress, cancelled) -> result`` that uses
only the core (numpy/scipy, never ``bpy``). When invoked from the UI, ``work`` runs in a
worker thread while a timer updates the status-bar progress bar; Esc or right-click sets
the cancel flag, the core raises :class:`~ssm_addon.base.errors.Cancelled` at its next check
and the scene is left as it was. ``finish(context, result)`` writes results back to
``bpy`` on the main thread. Called from a script (``bpy.ops.ssm.x()``, headless tests),
``execute`` runs the same two steps synchronously.
"""

from __future__ import annotations

import threading
import traceback

import bpy

from ssm_addon.base.errors import Cancelled, SSMError


class BackgroundJob:
    """Mixin for operators; subclasses implement ``prepare`` and ``finish``."""

    _timer = None
    _thread = None

    # -- subclass API: ``prepare(context)`` returns ``work(progress, cancelled)`` (or None
    # to abort) after reading its inputs from bpy; ``finish(context, result)`` writes the
    # result back on the main thread and returns an operator result set (or None).
    def partial(self, context, state):
        """Called on cancel/error with the job state (override to keep partial results)."""

    # -- synchronous path -----------------------------------------------------------
    def execute(self, context):
        try:
            work = self.prepare(context)
            if work is None:
                return {"CANCELLED"}
            result = work(self._print_progress, lambda: False)
        except Cancelled as err:
            self.partial(context, {"error": err})
            self.report({"WARNING"}, f"{self.bl_label}: cancelled ({err}); the scene is as it was")
            return {"CANCELLED"}
        except SSMError as err:
            self.report({"ERROR"}, str(err))
            return {"CANCELLED"}
        return self.finish(context, result) or {"FINISHED"}

    def _print_progress(self, fraction, message):
        if bpy.app.background:
            print(f"[{fraction * 100:5.1f} %] {message}", flush=True)

    # -- modal path -------------------------------------------------------------------
    def invoke(self, context, event):
        try:
            work = self.prepare(context)
        except SSMError as err:
            self.report({"ERROR"}, str(err))
            return {"CANCELLED"}
        if work is None:
            return {"CANCELLED"}
        self._state = {"fraction": 0.0, "message": "", "result": None, "error": None, "cancel": False, "done": False}
        state = self._state

        def progress(fraction, message):
            state["fraction"], state["message"] = fraction, message

        def run():
            try:
                state["result"] = work(progress, lambda: state["cancel"])
            except BaseException as err:  # noqa: BLE001 - handed to the main thread
                state["error"] = err
                if not isinstance(err, SSMError):
                    traceback.print_exc()
            finally:
                state["done"] = True

        self._thread = threading.Thread(target=run, daemon=True)
        self._thread.start()
        wm = context.window_manager
        wm.progress_begin(0, 100)
        self._timer = wm.event_timer_add(0.1, window=context.window)
        wm.modal_handler_add(self)
        context.workspace.status_text_set(f"{self.bl_label}: starting (Esc to cancel)")
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        state = self._state
        if event.type in {"ESC", "RIGHTMOUSE"} and event.value == "PRESS":
            state["cancel"] = True
        if event.type != "TIMER":
            return {"RUNNING_MODAL"}
        wm = context.window_manager
        wm.progress_update(int(state["fraction"] * 100))
        context.workspace.status_text_set(
            f"{self.bl_label}: {state['message']} ({state['fraction'] * 100:.0f} %) - Esc to cancel"
        )
        if not state["done"]:
            return {"RUNNING_MODAL"}
        self._cleanup(context)
        err = state["error"]
        if isinstance(err, Cancelled):
            self.partial(context, state)
            self.report({"WARNING"}, f"{self.bl_label}: cancelled")
            return {"CANCELLED"}
        if err is not None:
            self.partial(context, state)
            self.report({"ERROR"}, str(err))
            return {"CANCELLED"}
        return self.finish(context, state["result"]) or {"FINISHED"}

    def _cleanup(self, context):
        wm = context.window_manager
        if self._timer is not None:
            wm.event_timer_remove(self._timer)
            self._timer = None
        wm.progress_end()
        context.workspace.status_text_set(None)

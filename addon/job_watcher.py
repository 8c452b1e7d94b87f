"""One watcher for every kind of background work the add-on starts (a compress session, a library batch or scene
report, the dependency installer): a Blender timer advances the work and mirrors its progress into the panel, so
the UI never waits; Cancel stops it; one piece of work per kind at a time."""
from __future__ import annotations

from typing import Callable

import bpy

from .job import default_python


class JobWatcher:
    """Watches one kind of background work. advance(work) -> bool runs on every tick (every `interval` seconds):
    it steps the work, mirrors its progress into the panel and returns False once the work has ended (the watcher
    then lets it go); stop(work) cancels it (Cancel)."""

    def __init__(self, name: str, advance: Callable[[object], bool], stop: Callable[[object], None],
                 interval: float = 0.25):
        self.name, self._advance, self._stop, self.interval = name, advance, stop, interval
        self.work = None

    @property
    def running(self) -> bool:
        return self.work is not None

    def start(self, work, first_interval: float = 0.1) -> None:
        """Watch `work` from now on (a Blender timer; the caller has started the work itself)."""
        if self.work is not None:
            raise RuntimeError(f"a {self.name} is already running")
        self.work = work
        bpy.app.timers.register(self.tick, first_interval=first_interval)

    def tick(self) -> float | None:
        """The timer: advance the work; the next interval, or None when it ended (the timer stops)."""
        work = self.work
        if work is None:
            return None
        try:
            going = self._advance(work)
        except BaseException:
            self.work = None
            raise
        redraw()
        if not going:
            self.work = None
            return None
        return self.interval

    def cancel(self) -> bool:
        """Stop the work (its own cancel: queued jobs dropped, temporary files removed); False when none ran."""
        work, self.work = self.work, None
        if work is None:
            return False
        self._stop(work)
        return True


def redraw() -> None:
    """Redraw every area of every window (the panel and the preferences show the progress)."""
    wm = bpy.context.window_manager
    for window in (wm.windows if wm else []):
        for area in window.screen.areas:
            area.tag_redraw()


def notify(title: str, lines: list[str], icon: str = "INFO") -> None:
    """Say that a background run ended (a popup at the mouse; nothing in background mode, where the events are
    printed). Timers have no operator to `report` through."""
    if bpy.app.background:
        return

    def draw(menu, context):
        for line in lines[:8]:
            menu.layout.label(text=line[:120])

    try:
        bpy.context.window_manager.popup_menu(draw, title=title, icon=icon)
    except (RuntimeError, AttributeError):  # no window to show it in (a timer between redraws)
        pass


def addon_prefs(context):
    """The add-on's preferences (None when it is not registered under this package's name)."""
    addon = context.preferences.addons.get(__package__)
    return addon.preferences if addon else None


def job_python(context) -> str:
    """The Python the background jobs run in: the preferences' path, else the one found beside the add-on."""
    prefs = addon_prefs(context)
    return (prefs.python_path if prefs and prefs.python_path else "") or default_python()

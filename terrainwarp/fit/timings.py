"""Where a fit's time goes, and what the user sees while it runs: :class:`Clock` (exclusive seconds per part of
the fit, :data:`PARTS`), :class:`Progress` (a tqdm bar with a total that refreshes at least every second and says
what it is doing, compiling included), and :func:`part` / :func:`say`, which the fit's modules call to charge the
part they are in and to tell the bar, through the fit that is running (:func:`running`; nothing when none is).

The parts (``FitResult.timings``):

* ``compile``: JAX tracing and compiling the relaxed model's programs (or reading them from the persistent
  compilation cache, :mod:`terrainwarp.fit.jaxrt`);
* ``relaxed``: the relaxed model's optimiser (:func:`terrainwarp.fit.optimise.reduced_gradient`);
* ``hard``: the hard model and the polish on it (:mod:`terrainwarp.fit.search`);
* ``probes``: the error probes and the models' data (:mod:`terrainwarp.fit.families`), ``import jax`` included;
* ``exact``: the exact frames (the references a fit draws itself, the tries, the validation);
* ``other``: the rest (Python between the parts).

Each second is charged to one part (the innermost open one), so the parts add up to the fit's wall time.
"""

from __future__ import annotations

import contextvars
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ["PARTS", "Clock", "Progress", "running", "part", "say", "tick"]

PARTS = ("compile", "relaxed", "hard", "probes", "exact", "other")


class Clock:
    """Exclusive wall seconds per part (:data:`PARTS`): time inside a nested part counts only there. Opened on
    ``other`` when made; :meth:`close` ends it and returns the seconds of each part."""

    def __init__(self) -> None:
        self.seconds = dict.fromkeys(PARTS, 0.0)
        self._stack: list[list] = [["other", time.perf_counter()]]

    def enter(self, name: str) -> None:
        if name not in self.seconds:
            raise ValueError(f"name: expected one of {PARTS}, got {name!r}")
        now = time.perf_counter()
        top = self._stack[-1]
        self.seconds[top[0]] += now - top[1]
        self._stack.append([name, now])

    def leave(self) -> None:
        now = time.perf_counter()
        name, since = self._stack.pop()
        self.seconds[name] += now - since
        if self._stack:
            self._stack[-1][1] = now

    def close(self) -> dict[str, float]:
        """End every open part; the seconds of each."""
        while self._stack:
            self.leave()
        return dict(self.seconds)


class Progress:
    """A tqdm bar on stderr (``leave=False``), or nothing when disabled. Call it to advance one step;
    :meth:`say` shows what the fit is doing now. While the bar is open a helper thread redraws it every
    ``refresh_s`` (its elapsed time moves), so it never sits still for long, even inside one long step."""

    def __init__(self, enabled: bool, total: int, desc: str, refresh_s: float = 1.0) -> None:
        self.bar = None
        self.refreshes = 0
        self._stop = threading.Event()
        self._thread = None
        if enabled:
            from tqdm import tqdm  # lazy: heavy optional dependency

            self.bar = tqdm(total=total, desc=desc, unit="step", leave=False, file=sys.stderr)
            self._thread = threading.Thread(target=self._beat, args=(refresh_s,), daemon=True,
                                            name="terrainwarp-fit-progress")
            self._thread.start()

    def _beat(self, every: float) -> None:
        while not self._stop.wait(every):
            bar = self.bar
            if bar is None:
                return
            bar.refresh()
            self.refreshes += 1

    def __call__(self) -> None:
        if self.bar is not None:
            self.bar.update(1)

    def say(self, text: str) -> None:
        """Show ``text`` after the bar (what the fit is doing)."""
        if self.bar is not None:
            self.bar.set_postfix_str(text, refresh=True)

    def expect(self, remaining: int) -> None:
        """Set the total to the steps done plus ``remaining``."""
        if self.bar is not None:
            self.bar.total = self.bar.n + remaining
            self.bar.refresh()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        if self.bar is not None:
            self.bar.close()
            self.bar = None


_current: contextvars.ContextVar = contextvars.ContextVar("terrainwarp_fit_run", default=None)


@contextmanager
def running(clock: Clock, progress: Progress | None = None) -> Iterator[None]:
    """Make ``clock`` and ``progress`` the ones :func:`part`, :func:`say` and :func:`tick` reach inside the
    block."""
    token = _current.set((clock, progress))
    try:
        yield
    finally:
        _current.reset(token)


@contextmanager
def part(name: str) -> Iterator[None]:
    """Charge the block to ``name`` on the running fit's clock (nothing when no fit is running)."""
    run = _current.get()
    if run is None:
        yield
        return
    run[0].enter(name)
    try:
        yield
    finally:
        run[0].leave()


def say(text: str) -> None:
    """Show ``text`` on the running fit's progress bar (nothing when there is none)."""
    run = _current.get()
    if run is not None and run[1] is not None:
        run[1].say(text)


def tick() -> None:
    """Advance the running fit's progress bar one step."""
    run = _current.get()
    if run is not None and run[1] is not None:
        run[1]()

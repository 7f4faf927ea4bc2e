"""When an interactive session steps: at the wall clock (real time) or once per received pose (lock step).

Real time: a step is due every dt of wall time. A machine that keeps up sleeps between steps (real-time
factor 1); one that cannot steps back to back (the factor falls below 1, shown in the window and sent with
every step).
Simulated time never jumps and no step is skipped: a late step only starts later.

Lock step (``--lockstep``): each valid pose received on the stream gives exactly one step at that pose (within
the speed bound), answered before the next pose is read: a controller that owns the clock (a robot simulator,
a test) gets a deterministic run.
"""

from __future__ import annotations

import queue
import time as clock

__all__ = ["Pacer"]


class Pacer:
    """Takes a session's due steps and sends each step's report to the pose stream.

    Parameters
    ----------
    session : The :class:`refsim.interactive.session.InteractiveSession`.
    server : The :class:`refsim.interactive.server.PoseServer`, or None (keyboard only).
    lockstep : One step per received pose instead of the wall clock (needs ``server``).
    max_steps : Steps before the session ends by itself (the last is :meth:`InteractiveSession.finish`'s);
        None: until stopped.
    on_step : Called with each step's :class:`~refsim.interactive.session.StepReport`.
    """

    def __init__(
        self, session, server=None, *, lockstep: bool = False, max_steps: int | None = None, on_step=None
    ):
        if lockstep and server is None:
            raise ValueError("--lockstep needs the pose stream (--socket PORT)")
        self.session = session
        self.server = server
        self.lockstep = lockstep
        self.max_steps = max_steps
        self.on_step = on_step
        self._next = None  # wall-clock time the next real-time step is due [s]

    @property
    def done(self) -> bool:
        """The session reached ``max_steps`` (less its final step) or was finished."""
        if self.session.finished:
            return True
        return self.max_steps is not None and self.session.state.step >= self.max_steps - 1

    def start_clock(self) -> None:
        """Real time starts now (the first step is due at once)."""
        self._next = clock.perf_counter()

    def pump(self, budget: float) -> int:
        """Take the due steps for at most ``budget`` seconds of wall time; return how many were taken."""
        deadline = clock.perf_counter() + budget
        taken = 0
        while not self.done and clock.perf_counter() < deadline:
            if self.lockstep:
                try:
                    base, direction = self.server.poses.get_nowait()
                except queue.Empty:
                    break
                self.session.target.set(base, direction)
            else:
                now = clock.perf_counter()
                if self._next is None:
                    self._next = now
                if now < self._next:
                    break
                # behind by more than a step: restart the clock from now (no catching up in bursts)
                self._next = max(self._next + self.session.dt, now)
            self._report(self.session.step())
            taken += 1
        return taken

    def wait_time(self) -> float:
        """Seconds until the next step is due (real time), or a short poll interval (lock step) [s]."""
        if self.lockstep or self._next is None:
            return 0.002
        return max(0.0, self._next - clock.perf_counter())

    def finish(self) -> None:
        """End the session (its final step is reported too)."""
        session = self.session
        if session.finished:
            return
        before = session.state.step
        session.finish()
        if session.state.step > before and session.last_record is not None:
            self._report(_last_report(session))

    def _report(self, report) -> None:
        if self.server is not None:
            self.server.broadcast(report.message())
        if self.on_step is not None:
            self.on_step(report)


def _last_report(session):
    from refsim.interactive.session import StepReport

    record = session.last_record
    return StepReport(
        step=record.step,
        time=record.time,
        force=record.needle_force,
        phase=str(record.phase),
        events=tuple(event.name for event in record.events),
        base=session.target.applied_base,
        direction=session.target.applied_direction,
        real_time_factor=session.real_time_factor,
    )

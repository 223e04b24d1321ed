"""Replaying recorded sessions (docs/REPLAY.md).

``motcomp.replay.plan``
    What the service did, tick by tick, rebuilt from a recording (:class:`TickPlan`).
``motcomp.replay.reference``, ``motcomp.replay.engine``
    The compensator over a plan: the service's own tick (the reference) or the offline engine
    (vectorised reference, ``lfilter`` on the linear PID loop, exact limiter where it acts).
``motcomp.replay.analysis``, ``motcomp.replay.plots``, ``motcomp.replay.offline``
    Delays, saturation and differences from the recording; figures; the whole offline run.
``motcomp.replay.realtime``
    Republishing recorded inputs on zenoh on their recorded schedule.
``motcomp.replay.synth``
    Synthetic sessions through the service's own code, for tests and benchmarks.
"""

from motcomp.replay.plan import TickPlan, build_plan

__all__ = ["TickPlan", "build_plan"]

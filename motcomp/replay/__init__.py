"""Replaying recorded sessions (docs/REPLAY.md).

``motcomp.replay.plan``
    What the service did, tick by tick, rebuilt from a recording (:class:`TickPlan`).
``motcomp.replay.engine``
    The service's own tick (:func:`motcomp.core.tick.step`) over a plan, on the recorded bytes.
``motcomp.replay.analysis``, ``motcomp.replay.plots``, ``motcomp.replay.offline``
    Delays, saturation and differences from the recording; figures; the whole offline run.
``motcomp.replay.realtime``
    Republishing recorded inputs on zenoh on their recorded schedule.
``motcomp.replay.synth``
    Synthetic sessions through the service's own code, for tests and benchmarks.
"""

from motcomp.replay.plan import TickPlan, build_plan

__all__ = ["TickPlan", "build_plan"]

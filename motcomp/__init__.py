"""motcomp: identify a motion platform's lag and cancel most of it in software.

The package is organised by architecture:

``motcomp.core``
    Pure, clock-free math: process models, discretisation, PID gains and tuning rules,
    saturation, the pseudo open-loop compensator.  Imports numpy only.
``motcomp.design``
    Offline evaluation (frequency and time domain), reports and plots.
``motcomp.sim``
    The simulated platform (truth dynamics and sensor imperfections).
``motcomp.cli``
    The ``motcomp`` command.
"""

from motcomp.core.axes import AXES

__version__ = "0.1.0"

__all__ = ["AXES", "__version__"]

"""Platform identification: excite an axis, load what was measured, fit process models, report.

The first half of the method: measure the platform, so that the compensator's internal model is
the platform's real one.

=====================  ===========================================================================
module                 what it holds
=====================  ===========================================================================
``excitation``         low-pass pseudo-white noise, log swept sine, Schroeder multisine; scaled
                       to the axis limits (verified on the samples), faded in and out; CSV and
                       setpoint-stream writers
``data``               :class:`~motcomp.ident.data.Recording`; loaders chosen by file suffix
                       (CSV ``t,cmd,acc``, MCAP session recordings); checks and resampling
``structures``         the fitted model structures (P1D, P2D, P2UZD, OE): their parameters,
                       starting grids and regressors
``fit``                the output-error fit in the acceleration domain with the delay bracketed,
                       profiled and polished; standard errors, fit %, VAF, AIC; model selection
``report``             Table 1 of the paper per axis, JSON, markdown, figures, config fragment
=====================  ===========================================================================

The modules import scipy and matplotlib at their top; import them from the command handlers,
not at start-up.
"""

from __future__ import annotations

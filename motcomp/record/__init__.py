"""Session recording to MCAP and reading recordings back.

``motcomp record`` (:mod:`motcomp.record.recorder`) writes the wire traffic of a session in the
layout of docs/RECORDING.md; :func:`read_session` reads it back as numpy arrays (fast: frames are
decoded in bulk, see :mod:`motcomp.record.frames`), including a file cut short by a crash.

>>> from motcomp.record import read_session                       # doctest: +SKIP
>>> s = read_session("session.mcap")                              # doctest: +SKIP
>>> t, cmd, acc = s.identification_data("rails_y")                # doctest: +SKIP
"""

from motcomp.record.session import (
    DEFAULT_KEYS,
    FeedbackStream,
    InputStream,
    OutputStream,
    RawStream,
    Session,
    read_session,
    session_parts,
)

__all__ = [
    "DEFAULT_KEYS",
    "FeedbackStream",
    "InputStream",
    "OutputStream",
    "RawStream",
    "Session",
    "read_session",
    "session_parts",
]

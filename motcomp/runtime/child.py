"""A helper process of the service, spoken to over its stdin and stdout: one implementation
for the reload reader (:mod:`motcomp.runtime.reload`) and the model estimator
(:mod:`motcomp.runtime.supervise`).

Messages are pickles behind a 4-byte length.  The child runs in a session of its own (a
terminal's Ctrl-C is the service's) and ends when its stdin closes -- also when the service dies
without a word, so that no helper outlives it.
"""

from __future__ import annotations

import os
import pickle
import select
import struct
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any

__all__ = ["ask", "recv", "send", "serve", "spawn", "wait_readable"]

_HEADER = struct.Struct("!I")


def send(f: IO[bytes], obj: Any) -> None:
    """Write one message."""
    data = pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
    f.write(_HEADER.pack(len(data)) + data)
    f.flush()


def _exact(f: IO[bytes], n: int) -> bytes:
    data = f.read(n)
    if data is None or len(data) != n:
        raise EOFError
    return data


def recv(f: IO[bytes]) -> Any:
    """Read one message (EOFError at the end of the stream)."""
    (n,) = _HEADER.unpack(_exact(f, _HEADER.size))
    return pickle.loads(_exact(f, n))


def wait_readable(f: IO[bytes], timeout_s: float) -> bool:
    """Whether ``f`` has something to read within ``timeout_s`` (the wait releases the
    interpreter)."""
    return bool(select.select([f], [], [], timeout_s)[0])


def ask(proc: subprocess.Popen[bytes], request: Any, timeout_s: float) -> Any:
    """Send ``request`` to the child ``proc`` and return its reply.

    Raises
    ------
    TimeoutError
        No reply within ``timeout_s``.
    OSError, EOFError, pickle.PickleError
        The child is gone or its reply is not a message.
    """
    assert proc.stdin is not None and proc.stdout is not None
    send(proc.stdin, request)
    if not wait_readable(proc.stdout, timeout_s):
        raise TimeoutError
    return recv(proc.stdout)


def spawn(main: str) -> subprocess.Popen[bytes]:
    """Start ``python -c "<main>"`` (e.g. ``from motcomp.runtime.reload import serve;
    serve()``) with this checkout's motcomp importable, its stdin and stdout piped."""
    import motcomp

    env = dict(os.environ)
    root = str(Path(motcomp.__file__).resolve().parent.parent)
    env["PYTHONPATH"] = root + os.pathsep + env.get("PYTHONPATH", "")
    return subprocess.Popen([sys.executable, "-c", main], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, env=env, close_fds=True,
                            start_new_session=True)


def serve(handle: Callable[[Any], Any]) -> None:
    """The child's main loop: answer each message on stdin with ``handle(message)`` on stdout
    until stdin closes (anything printed goes to stderr)."""
    stdin = sys.stdin.buffer
    stdout = os.fdopen(os.dup(1), "wb")  # the replies' own
    os.dup2(2, 1)
    sys.stdout = sys.stderr
    while True:
        try:
            message = recv(stdin)
        except EOFError:
            return
        send(stdout, handle(message))

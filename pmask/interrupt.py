"""A Ctrl-C that is not lost.

Some libraries swallow ``KeyboardInterrupt``: trimesh wraps each optional import in ``except BaseException``
(114 places), so a Ctrl-C that lands while one of them is imported became a stored exception and the command
ran on to its end (tests/test_robustness.py saw a precompute ignore it for over 30 s on a loaded machine).
The ``pmask`` command's handler for SIGINT and SIGTERM records the request here before raising, and the
long-running steps call :func:`check` where they start (each precompute stage, the remesh worker's launch),
so a swallowed interrupt still ends the command at the next of them.
"""
from __future__ import annotations

_pending = False


def handler(signum, frame) -> None:
    """SIGINT/SIGTERM: remember the request, then raise it where the main thread is."""
    global _pending
    _pending = True
    raise KeyboardInterrupt


def check() -> None:
    """Raise ``KeyboardInterrupt`` if an interrupt was requested (and perhaps swallowed on its way)."""
    if _pending:
        raise KeyboardInterrupt


def clear() -> None:
    """Forget a request (the command has reported it)."""
    global _pending
    _pending = False

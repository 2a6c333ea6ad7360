"""Warp's console output while abd_gym is used as a library.

Warp 1.19 prints its init banner and a ``Module <name> load on device '<device>' took ... ms``
line for every kernel module it loads when ``warp.config.log_level`` is ``warp.LOG_INFO`` (its
default; ``warp.config.quiet`` is no longer read).  Importing abd_gym raises that default to
``warp.LOG_WARNING``: warnings and errors still print, the per-module lines do not.

Warp's native library also prints ``Warp CUDA warning: Could not find or load the NVIDIA CUDA
driver. GPU execution will not be available.`` when it initialises on a machine without a CUDA
driver, whatever the level: on the CPU-only machine abd_gym is meant to run on as well, that is
no news.  Importing abd_gym initialises Warp with the native library's standard error captured
and writes back every line of it but that one.

To see Warp's messages again (that line included): set the environment variable
``ABD_GYM_VERBOSE=1`` before the import, set ``warp.config.log_level`` to another level before
importing abd_gym (a level other than the default is kept), or set it after the import::

    import warp as wp
    wp.config.log_level = wp.LOG_INFO     # or wp.LOG_DEBUG
"""
from __future__ import annotations

import os
import sys
import tempfile

import warp as wp

VERBOSE_ENV = "ABD_GYM_VERBOSE"
# the native library's line on a machine without a CUDA driver (Warp 1.x)
NO_DRIVER = "Warp CUDA warning: Could not find or load the NVIDIA CUDA driver"


def verbose_requested() -> bool:
    """Whether ``$ABD_GYM_VERBOSE`` asks for Warp's messages (set, and not "", "0", "false" or "no")."""
    return os.environ.get(VERBOSE_ENV, "").strip().lower() not in ("", "0", "false", "no")


def quiet_warp() -> None:
    """Warp's log level to ``LOG_WARNING`` where it is Warp's default (``LOG_INFO``) and
    ``$ABD_GYM_VERBOSE`` does not ask for its messages; then Warp initialised without its
    no-CUDA-driver line (``init_without_driver_line``)."""
    if verbose_requested() or wp.config.log_level != wp.LOG_INFO:
        return
    wp.config.log_level = wp.LOG_WARNING
    init_without_driver_line()


def init_without_driver_line() -> None:
    """``wp.init()`` with file descriptor 2 (the native library's standard error) sent to a
    temporary file, whose lines, but NO_DRIVER's, are written back to ``sys.stderr``."""
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile(mode="w+b") as captured:
        os.dup2(captured.fileno(), 2)
        try:
            wp.init()
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        captured.seek(0)
        text = captured.read().decode("utf-8", "replace")
    kept = [line for line in text.splitlines(keepends=True) if not line.startswith(NO_DRIVER)]
    if kept:
        sys.stderr.write("".join(kept))
        sys.stderr.flush()

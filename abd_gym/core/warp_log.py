"""Warp's console output while abd_gym is used as a library.

Warp 1.19 prints its init banner and a ``Module <name> load on device '<device>' took ... ms``
line for every kernel module it loads when ``warp.config.log_level`` is ``warp.LOG_INFO`` (its
default; ``warp.config.quiet`` is no longer read).  Importing abd_gym raises that default to
``warp.LOG_WARNING``: warnings and errors still print, the per-module lines do not.

To see Warp's messages again: set the environment variable ``ABD_GYM_VERBOSE=1`` before the import,
set ``warp.config.log_level`` to another level before importing abd_gym (a level other than the
default is kept), or set it after the import::

    import warp as wp
    wp.config.log_level = wp.LOG_INFO     # or wp.LOG_DEBUG

(Warp's native library prints a "Warp CUDA warning" of its own on a machine without a CUDA
driver, whatever the level.)
"""
from __future__ import annotations

import os

import warp as wp

VERBOSE_ENV = "ABD_GYM_VERBOSE"


def verbose_requested() -> bool:
    """Whether ``$ABD_GYM_VERBOSE`` asks for Warp's messages (set, and not "", "0", "false" or "no")."""
    return os.environ.get(VERBOSE_ENV, "").strip().lower() not in ("", "0", "false", "no")


def quiet_warp() -> None:
    """Warp's log level to ``LOG_WARNING`` where it is Warp's default (``LOG_INFO``) and
    ``$ABD_GYM_VERBOSE`` does not ask for its messages."""
    if not verbose_requested() and wp.config.log_level == wp.LOG_INFO:
        wp.config.log_level = wp.LOG_WARNING

"""Process hygiene for the process that runs stages (a prefork child, or the solo worker).

pycolmap installs glog's fatal-signal handlers when it is imported. After a native crash (a heap corruption
in a compiled kernel, say) that handler calls ``backtrace()``, which needs ``malloc``, which is locked by the
crash: the process then hangs forever instead of dying, and Celery never learns that its task is lost (seen
on this project's machines). So before the first stage, import pycolmap once ourselves, put the default
actions back for the fatal signals (with ``faulthandler`` printing the Python stack first) and restore the
SIGTERM handler it replaced. A crashed child then dies, Celery requeues its task (reject on worker lost), and
the stage resumes from its marker/checkpoint; ``max_stage_attempts`` stops a stage that crashes every time.
"""

from __future__ import annotations

import faulthandler
import logging
import signal
import sys
import threading

log = logging.getLogger(__name__)

FATAL_SIGNALS = (signal.SIGSEGV, signal.SIGABRT, signal.SIGBUS, signal.SIGILL, signal.SIGFPE)
_prepared = False  # once per process: the handlers are process-wide


def prepare_stage_process() -> None:
    global _prepared
    if _prepared or threading.current_thread() is not threading.main_thread():
        return  # signal handlers can only be set from the main thread (a threads pool keeps glog's)
    previous_term = signal.getsignal(signal.SIGTERM)
    try:
        # lazy: pycolmap is heavy and native; only the stage process may load it, once, to undo its handlers
        import pycolmap  # noqa: F401  (installs glog's handlers; undone just below)
    except ImportError:
        pass
    for sig in FATAL_SIGNALS:
        signal.signal(sig, signal.SIG_DFL)
    if previous_term is not None:
        signal.signal(signal.SIGTERM, previous_term)
    faulthandler.enable(file=sys.__stderr__, all_threads=True)
    _prepared = True
    log.debug("fatal signal handlers reset to their defaults (faulthandler on)")

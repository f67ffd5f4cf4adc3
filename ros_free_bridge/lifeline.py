"""Child processes that end when the bridge ends, however it ends.

The bridge starts helper processes (the generator, the bus emulator). A parent that exits
normally stops them, but one killed with SIGKILL (or by the OOM killer) runs no code, and
its children live on: a generator computing for nobody, an emulator holding a pty. A child
calls :func:`die_with_parent` first thing; it then ends when its parent does, by two means:

1. Linux's ``prctl(PR_SET_PDEATHSIG, SIGKILL)``: the kernel kills the child when the thread
   that started it ends. That thread must live as long as the parent (the main thread, as
   for the command line), so the parent says whether it is (``pdeathsig``); else only (2).
2. A watcher thread that checks every ``poll_s`` whether the child was re-parented (its
   parent process id changed: the parent is gone), and then exits at once. This works
   everywhere and also covers a parent that died before (1) was in place.
"""

from __future__ import annotations

import ctypes
import os
import signal
import sys
import threading

PR_SET_PDEATHSIG = 1  #: from <linux/prctl.h>


def parent_thread_lives_on() -> bool:
    """Whether a child started from the calling thread may use PR_SET_PDEATHSIG: the calling
    thread is the main thread, which lives as long as the process."""
    return threading.current_thread() is threading.main_thread()


def set_pdeathsig(sig: int = signal.SIGKILL) -> bool:
    """Ask the kernel to send ``sig`` to this process when its parent thread ends (Linux
    only); True when in place."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        return libc.prctl(PR_SET_PDEATHSIG, int(sig), 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


def die_with_parent(parent_pid: int, *, pdeathsig: bool = True, poll_s: float = 0.25) -> None:
    """End this process when process ``parent_pid`` (its parent) ends (module docstring)."""
    if pdeathsig:
        set_pdeathsig(signal.SIGKILL)
    if os.getppid() != parent_pid:  # the parent died before the line above took effect
        os._exit(0)

    def watch() -> None:
        while True:
            threading.Event().wait(poll_s)
            if os.getppid() != parent_pid:
                os._exit(0)  # nothing to clean up that is worth outliving the bridge

    threading.Thread(target=watch, name="lifeline", daemon=True).start()

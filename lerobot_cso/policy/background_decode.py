"""One decode running in a background thread, so a control loop keeps ticking while the next skill is sampled."""

from __future__ import annotations

import os
import threading
from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor


class BackgroundDecode:
    """Runs ``decode(batch)`` under ``torch.inference_mode`` in a thread; ``result()`` waits for it.

    Torch kernels release the GIL, so the caller's thread runs on while the decode computes; an exception in
    the decode is re-raised by ``result()``. With ``nice > 0`` the thread lowers its own scheduling priority
    (Linux: per-thread niceness) so that the control loop and the robot's I/O threads preempt it; with one
    intra-op thread (``torch.set_num_threads(1)``) the whole decode runs in this thread. The thread is not a
    daemon: a process that exits while a decode runs waits for it (one skill, well under a second) instead of
    tearing torch down under it, which aborts the process ("terminate called without an active exception").
    """

    def __init__(self, decode: Callable[[dict[str, Any]], Tensor], batch: dict[str, Any], nice: int = 0) -> None:
        self._decode = decode
        self._batch = batch
        self._nice = nice
        self._value: Tensor | None = None
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="cso-decode")
        self._thread.start()

    def _run(self) -> None:
        try:
            if self._nice and hasattr(os, "setpriority"):
                tid = threading.get_native_id()
                os.setpriority(os.PRIO_PROCESS, tid, os.getpriority(os.PRIO_PROCESS, tid) + self._nice)
            with torch.inference_mode():
                self._value = self._decode(self._batch)
        except BaseException as error:  # handed to the caller's thread by result()
            self._error = error

    def result(self) -> Tensor:
        """The decoded tensor, once the thread has finished."""
        self._thread.join()
        if self._error is not None:
            raise self._error
        assert self._value is not None
        return self._value

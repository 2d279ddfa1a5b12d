"""One decode running in a background thread, so a control loop keeps ticking while the next skill is sampled."""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor


class BackgroundDecode:
    """Runs ``decode(batch)`` under ``torch.inference_mode`` in a thread; ``result()`` waits for it.

    Torch kernels release the GIL, so the caller's thread runs on while the decode computes; an exception in
    the decode is re-raised by ``result()``. The thread is not a daemon: a process that exits while a decode
    runs waits for it (one skill, well under a second) instead of tearing torch down under it, which aborts
    the process ("terminate called without an active exception").
    """

    def __init__(self, decode: Callable[[dict[str, Any]], Tensor], batch: dict[str, Any]) -> None:
        self._decode = decode
        self._batch = batch
        self._value: Tensor | None = None
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="cso-decode")
        self._thread.start()

    def _run(self) -> None:
        try:
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

"""The next skill's decode off the control loop's thread: in a background thread, or in a decode process."""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any, Protocol

import torch
from torch import Tensor

DECODE_WORKERS = ("thread", "process")


class PendingDecode(Protocol):
    def result(self) -> Tensor:
        """The decoded chunk; waits for it."""


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


def _serve(conn: Any, config: Any, state: dict[str, Tensor]) -> None:
    """The decode process: a copy of the policy, one intra-op thread; decodes each batch it is sent."""
    from lerobot_cso.policy.modeling_cso import CSOPolicy

    torch.set_num_threads(1)
    try:
        policy = CSOPolicy(config)
        policy.load_state_dict(state)
        policy.eval()
        conn.send("ready")
    except Exception as error:
        conn.send(error)
        return
    while True:
        try:
            batch = conn.recv()
        except (EOFError, OSError):  # the policy's process is gone
            return
        if batch is None:
            return
        try:
            with torch.inference_mode():
                conn.send(policy.executed_chunk(batch))
        except Exception as error:
            conn.send(error)


class DecodeProcess:
    """A spawned process holding a copy of the policy's weights that decodes skills for it.

    Its Python runs under its own interpreter lock, so the control loop's thread and the robot's I/O threads
    never wait for the decode's Python between kernels, as they do for a decode thread. It starts in the
    background (importing torch takes seconds): until :meth:`ready`, the caller decodes in a thread. Sampling
    draws from the process's own random stream; the weights are those at start (``close`` it when they change).
    """

    def __init__(self, config: Any, state: dict[str, Tensor]) -> None:
        context = torch.multiprocessing.get_context("spawn")
        self._conn, child = context.Pipe()
        self._process = context.Process(target=_serve, args=(child, config, state), name="cso-decode", daemon=True)
        self._process.start()
        child.close()
        self._ready = False
        self._busy = False
        self.submitted = 0  # decodes sent to the process

    def ready(self) -> bool:
        """Whether the process has started and is idle; raises if it failed to start."""
        if not self._ready and self._conn.poll():
            message = self._conn.recv()
            if isinstance(message, BaseException):
                raise RuntimeError(f"the decode process did not start: {message}") from message
            self._ready = True
        return self._ready and not self._busy

    def submit(self, batch: dict[str, Any]) -> PendingDecode:
        """Send ``batch`` (call only when :meth:`ready`); the handle's ``result()`` waits for the chunk."""
        self._busy = True
        self.submitted += 1
        self._conn.send(batch)
        return _ProcessResult(self)

    def _receive(self) -> Tensor:
        message = self._conn.recv()
        self._busy = False
        if isinstance(message, BaseException):
            raise message
        return message

    def close(self) -> None:
        """Ask the process to end; killed if it does not within a second."""
        try:
            self._conn.send(None)
        except (BrokenPipeError, OSError):
            pass
        self._process.join(timeout=1.0)
        if self._process.is_alive():
            self._process.kill()
        self._conn.close()


class _ProcessResult:
    def __init__(self, worker: DecodeProcess) -> None:
        self._worker, self._value = worker, None

    def result(self) -> Tensor:
        if self._value is None:
            self._value = self._worker._receive()
        return self._value

"""The next skill decoded in a process of its own, so a control loop keeps ticking while it is sampled."""

from __future__ import annotations

import io
import multiprocessing
import os
import pickle
from multiprocessing.connection import Connection
from typing import Any

import numpy as np
import torch
from torch import Tensor

# History (docs/benchmarks.md): on the PiPER twin's 30 Hz loop the late ticks were mostly the ticks that started a
# decode, first because the decode took the CPU from the loop (session 26: a decode thread, niced below the loop),
# then because a decode *thread*, however low its priority, took the GIL from the loop between a tick's
# select_action and its send (session 35: 82-96 % of the late ticks; a start delay halved them). A process has a
# GIL of its own (session 36: about half the late ticks of the thread's in the same runs, the spike at the tick after
# the hand-over gone); at SCHED_IDLE, the lowest CPU priority, the hand-over tick itself stands out less than at
# niceness +5, though still a little in most runs.


def _to_numpy(batch: dict[str, Any]) -> dict[str, Any]:
    """Tensors as numpy arrays: pickled ~10x faster than tensors (a 64x64 camera batch: ~20 us against ~200 us)."""
    return {k: v.detach().cpu().numpy() if isinstance(v, Tensor) else v for k, v in batch.items()}


def _serve(conn: Connection, policy_class: type, config: Any, state: bytes, seed: int) -> None:
    """The decode process: its own copy of the policy, one batch at a time."""
    if hasattr(os, "SCHED_IDLE"):  # Linux: also below a real-time (SCHED_FIFO) caller, whose policy it inherits
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    else:
        os.nice(19)
    torch.set_num_threads(1)
    torch.manual_seed(seed)
    policy = policy_class(config)
    policy.load_state_dict(torch.load(io.BytesIO(state), weights_only=True))
    device = torch.device(config.device or "cpu")
    policy.to(device).eval()
    conn.send_bytes(pickle.dumps(os.getpid()))
    while True:
        try:
            request = conn.recv_bytes()
        except EOFError:  # the policy's process closed its end or exited
            return
        try:
            batch = pickle.loads(request)
            batch = {k: torch.from_numpy(v).to(device) if isinstance(v, np.ndarray) else v for k, v in batch.items()}
            with torch.inference_mode():
                reply = (None, policy._executed_chunk(batch).cpu().numpy())
        except Exception as error:  # noqa: BLE001 - handed to the caller, which re-raises it
            reply = (error, None)
        try:
            message = pickle.dumps(reply, protocol=5)
        except Exception:  # noqa: BLE001 - an error that does not pickle reaches the caller as its text
            message = pickle.dumps((RuntimeError(f"in the decode process: {reply[0]!r}"), None))
        conn.send_bytes(message)


class PendingDecode:
    """The reply to one request to a ``DecodeProcess``; ``result()`` waits for it and re-raises its error."""

    def __init__(self, process: DecodeProcess, device: torch.device) -> None:
        self._process, self._device = process, device
        self._reply: tuple[Exception | None, np.ndarray | None] | None = None

    def result(self) -> Tensor:
        if self._reply is None:
            self._reply = self._process.receive()
        error, chunk = self._reply
        if error is not None:
            raise error
        return torch.from_numpy(chunk).to(self._device)


class DecodeProcess:
    """A copy of a policy in a spawned process at the lowest CPU priority (SCHED_IDLE), decoding the next skill's
    executed actions there (``policy._executed_chunk``) while the caller's loop ticks on.

    Requests and replies are pickled as numpy arrays on a pipe by the caller's own thread: the caller's process runs
    no helper thread (``concurrent.futures.ProcessPoolExecutor`` would run two, which take its GIL as a thread
    decode did). Replies come in the order of the requests; the policy keeps one pending at a time. Starting takes
    seconds (a Python with torch, and the policy rebuilt from its config and weights); the weights are those at the
    start. The process ends when this object is closed or dropped, or with the caller's process (it is a daemon).
    """

    def __init__(self, policy: torch.nn.Module) -> None:
        weights = io.BytesIO()
        torch.save({k: v.detach().cpu() for k, v in policy.state_dict().items()}, weights)
        seed = int(torch.randint(2**31 - 1, ()))  # drawn from the caller's generator
        context = multiprocessing.get_context("spawn")  # a fork would copy torch's threads' state mid-flight
        self._conn, child = context.Pipe()
        self._process = context.Process(
            target=_serve,
            args=(child, type(policy), policy.config, weights.getvalue(), seed),
            name="cso-decode",
            daemon=True,
        )
        self._process.start()
        child.close()
        self.pid: int = self.receive()

    def receive(self) -> Any:
        """The process's next message; a process that died (killed, out of memory) is a clear error."""
        try:
            return pickle.loads(self._conn.recv_bytes())
        except (EOFError, OSError):
            raise self._ended() from None

    def decode(self, batch: dict[str, Any]) -> PendingDecode:
        """Hand ``batch`` over: the process decodes from it while the caller goes on."""
        device = next((v.device for v in batch.values() if isinstance(v, Tensor)), torch.device("cpu"))
        try:
            self._conn.send_bytes(pickle.dumps(_to_numpy(batch), protocol=5))
        except OSError:
            raise self._ended() from None
        return PendingDecode(self, device)

    def _ended(self) -> RuntimeError:
        self._process.join(timeout=5)
        return RuntimeError(f"the decode process (pid {self._process.pid}) ended, exit code {self._process.exitcode}")

    def close(self) -> None:
        """End the process (it finishes a decode in progress first)."""
        self._conn.close()
        self._process.join(timeout=30)

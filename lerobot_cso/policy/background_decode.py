"""The next skill decoded on a background thread, so a control loop keeps ticking while it is sampled."""

from __future__ import annotations

import os
import sys
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any

import torch
from torch import Tensor

# The decode thread's niceness above the caller's (Linux, where niceness is per thread). On the PiPER twin's 30 Hz
# loop (docs/benchmarks.md, session 26) the late ticks were mostly the ticks that started a decode: the decode
# took the CPU from the loop's own thread before it had sent its action. Below the loop, p99 met 36.7 ms in 6 of 10
# runs (3 of ~25 at +0) and 4-29 ticks of ~1 640 were late (13-326 at +0); a decode still finishes within its lead.
# On a 2-core AMD VM (session 35) 82-96 % of the late ticks were still decode-start ticks, however low the decode's
# priority: it took the GIL, not the CPU, from the loop between that tick's select_action and its send. Hence the
# start delay (the policy's ``async_decode_delay_s``): 50-87 late ticks per 60 s run without it, 4-20 with 8 ms.
DECODE_NICENESS = 5
_decoder: tuple[int, ThreadPoolExecutor] | None = None  # the process that made it, and its one decode thread


def _below_the_caller() -> None:
    if sys.platform == "linux":
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), min(os.nice(0) + DECODE_NICENESS, 19))


def _under_inference_mode(decode: Callable[[dict[str, Any]], Tensor], batch: dict[str, Any], delay_s: float) -> Tensor:
    time.sleep(delay_s)
    with torch.inference_mode():
        return decode(batch)


def decode_in_background(
    decode: Callable[[dict[str, Any]], Tensor], batch: dict[str, Any], delay_s: float = 0.0
) -> Future[Tensor]:
    """``decode(batch)`` under ``torch.inference_mode`` on the process's one decode thread, ``delay_s`` after
    this call (the caller's tick goes on alone that long); the future's ``result()`` waits for it and re-raises
    what it raised.

    The thread is made by the first call and kept, at ``DECODE_NICENESS`` below the caller: handing it a decode
    is putting it on a queue, so the tick that starts a decode does not wait for a new thread to be scheduled
    (``Thread.start`` waits until the thread runs: 0.5 ms median, 4-5 ms p99 on the twin's loop). Torch kernels
    release the GIL, so the caller's thread runs on while the decode computes. At exit the interpreter waits for
    a decode in progress (``concurrent.futures`` joins its threads) instead of tearing torch down under it, which
    aborts the process ("terminate called without an active exception").
    """
    global _decoder
    if _decoder is None or _decoder[0] != os.getpid():  # a forked child has the parent's object, not its thread
        executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="cso-decode", initializer=_below_the_caller)
        _decoder = (os.getpid(), executor)
    return _decoder[1].submit(_under_inference_mode, decode, batch, delay_s)

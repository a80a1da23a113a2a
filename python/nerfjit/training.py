"""`nerfjit.Trainer`: a script's run whose training is followed step by step.

    trainer = nerfjit.Trainer("examples/train_box.sdf", set=["train.steps=2000"], out="box")
    for metrics in trainer.steps(every=100):      # the run starts here
        print(metrics["step"], metrics["loss"], metrics["psnr"])

Ctrl-C, wherever it lands (in nerfjit or in the loop's own code), asks training to stop at the end of its
step and write its checkpoint, then raises `KeyboardInterrupt`; `Trainer(..., resume=True)` continues from
the checkpoint. Leaving the loop early (`break`) stops training the same way once the iterator is closed or
collected, and the interpreter waits at exit for any training still stopping.
"""

import atexit
import signal
import threading
import weakref
from os import PathLike
from typing import Iterator, Optional, Sequence, Union

from . import _nerfjit

_live: "weakref.WeakSet[_nerfjit.Steps]" = weakref.WeakSet()
_previous_handler = None


def _on_sigint(signum, frame):
    """Ctrl-C: every live training is asked to stop; then what the handler before ours did."""
    for steps in list(_live):
        steps.stop()
    if callable(_previous_handler):
        _previous_handler(signum, frame)
    elif _previous_handler != signal.SIG_IGN:
        raise KeyboardInterrupt


def _close_all():
    for steps in list(_live):
        steps.close()


def _follow(steps: "_nerfjit.Steps") -> None:
    """Keeps `steps` where Ctrl-C and the interpreter's exit find it (the handler installed once, from the
    main thread, in front of the one there was)."""
    global _previous_handler
    if not _live and _previous_handler is None:
        atexit.register(_close_all)
    _live.add(steps)
    if _previous_handler is None and threading.current_thread() is threading.main_thread():
        _previous_handler = signal.getsignal(signal.SIGINT)
        signal.signal(signal.SIGINT, _on_sigint)


class Trainer:
    """A run of `script` (a path or an example's name) with `set` overrides, writing into `out`, resuming its
    checkpoint when `resume`, whose training `steps` follows."""

    def __init__(
        self,
        script: str,
        *,
        set: Sequence[str] = (),
        out: Optional[Union[str, PathLike]] = None,
        resume: bool = False,
    ):
        self._native = _nerfjit.Trainer(str(script), set=list(set), out=out, resume=resume)

    def steps(self, every: int = 100) -> Iterator[dict]:
        """Starts the run: the metrics at every `every`-th training step (the first step logged at or after
        it: the log holds every 10th) and at the last (`step`, `loss`, `psnr`, ...), as they come."""
        steps = self._native.steps(every)
        _follow(steps)
        return steps


__all__ = ["Trainer"]

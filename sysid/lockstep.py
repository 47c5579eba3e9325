"""Independent fits side by side, their predictions batched (docs/sysid.md, "Runtime").

A fit predicts a few hundred windows for 1 + p parameter vectors per least-squares step; at that size
numpy's per-call overhead is about half the time of a batched prediction (sysid.model). Fits that do
not depend on each other (each candidate alone, the trials of a selection round, leave-one-out refits)
run here in lockstep: each in its own thread (scipy's least_squares calls back into Python), and a
round starts when every running fit waits for a prediction; all requests of the round go to one
``sysid.model.predict`` call per model family and window set. Rounds therefore do not depend on thread
timing, and every fit sees exactly the predictions it would see alone (a prediction does not depend on
what else is in its batch, up to rounding).
"""

from __future__ import annotations

import dataclasses
import threading
from typing import Callable, Sequence, TypeVar

import numpy as np

from sysid import model
from sysid.data import Trajectory
from sysid.model import ModelSetup
from vehicles.params import Corrections

T = TypeVar("T")
_local = threading.local()
_NEUTRAL = Corrections()


def predict(traj: Trajectory, starts: np.ndarray, horizon: int, setup: ModelSetup | Sequence[ModelSetup]) -> np.ndarray:
    """``sysid.model.predict``; inside :func:`side_by_side` the request joins the round's batch."""
    rounds = getattr(_local, "rounds", None)
    if rounds is None:
        return model.predict(traj, starts, horizon, setup)
    return rounds.request((traj, np.asarray(starts, dtype=int), horizon, setup))


class _Rounds:
    def __init__(self) -> None:
        self.cond = threading.Condition()
        self.running = 0  # workers that are neither waiting for a prediction nor for their own sub-tasks
        self.pending: dict[tuple, tuple] = {}  # worker path -> request
        self.results: dict[tuple, object] = {}
        self.next_id = 0

    def request(self, req: tuple):
        me = _local.path
        with self.cond:
            self.pending[me] = req
            self.running -= 1
            self.cond.notify_all()
            while me not in self.results:
                self.cond.wait()
            out = self.results.pop(me)
        if isinstance(out, BaseException):
            raise out
        return out

    def serve(self) -> None:
        """Coordinator (the caller of side_by_side): one batch per round until every worker is done."""
        while True:
            with self.cond:
                while self.running > 0:
                    self.cond.wait()
                if not self.pending:
                    return
                batch = sorted(self.pending.items())  # worker order, not arrival order
                self.pending.clear()
            results = _serve_batch(batch)
            with self.cond:
                self.results.update(results)
                self.running += len(batch)
                self.cond.notify_all()


def _serve_batch(batch: list[tuple[tuple, tuple]]) -> dict[tuple, object]:
    groups: dict[tuple, list] = {}
    for who, (traj, starts, horizon, setup) in batch:
        setups = [setup] if isinstance(setup, ModelSetup) else list(setup)
        s0 = setups[0]
        # Setups stack when they differ in [corrections] only (sysid.model.predict).
        key = (id(traj), starts.tobytes(), horizon, s0.dynamic, s0.substeps,
               dataclasses.replace(s0.car, corrections=_NEUTRAL))
        groups.setdefault(key, []).append((who, traj, starts, horizon, setup, setups))
    out: dict[tuple, object] = {}
    for members in groups.values():
        _, traj, starts, horizon, _, _ = members[0]
        every = [s for m in members for s in m[5]]
        try:
            preds = model.predict(traj, starts, horizon, every)
        except BaseException as exc:  # every member gets the error its own call would have raised
            for m in members:
                out[m[0]] = exc
            continue
        preds.flags.writeable = False
        at = 0
        for who, _, _, _, setup, setups in members:
            out[who] = preds[at] if isinstance(setup, ModelSetup) else preds[at:at + len(setups)]
            at += len(setups)
    return out


def side_by_side(tasks: Sequence[Callable[[], T]]) -> list[T]:
    """Run the tasks in lockstep (their predictions batched per round); results in task order.
    Called from inside a task, the sub-tasks join the same rounds."""
    if len(tasks) <= 1:
        return [t() for t in tasks]
    outer = getattr(_local, "rounds", None)
    rounds = outer or _Rounds()
    parent = getattr(_local, "path", ())
    results: list = [None] * len(tasks)
    errors: list = [None] * len(tasks)
    left = [len(tasks)]

    def work(i: int) -> None:
        _local.rounds, _local.path = rounds, parent + (i,)
        try:
            results[i] = tasks[i]()
        except BaseException as exc:
            errors[i] = exc
        finally:
            with rounds.cond:
                left[0] -= 1
                # The last sub-task hands its running slot back to the waiting parent (no round can start
                # without the parent's next request).
                if not (left[0] == 0 and outer is not None):
                    rounds.running -= 1
                rounds.cond.notify_all()

    with rounds.cond:
        # A parent task's running slot passes to its sub-tasks while it waits for them.
        rounds.running += len(tasks) - (outer is not None)
    threads = [threading.Thread(target=work, args=(i,), name=f"sysid-fit-{parent + (i,)}", daemon=True)
               for i in range(len(tasks))]
    for t in threads:
        t.start()
    if outer is None:
        rounds.serve()
    for t in threads:
        t.join()
    for e in errors:
        if e is not None:
            raise e
    return results

"""The operator's stop key of a real-time race (docs/racing.md, "Live view and operator stop").

The loop asks :class:`OperatorStop` once a tick whether the operator asked to stop. The first time
the input says so, every car is sent neutral at once and ``stop: operator stop key - all cars
neutral`` is logged; from then on every check answers ``operator_stop`` and the loop ends the race
as it ends it for any other reason (shutdown, recording closed, summary). The input is injected: a
terminal key in a real race (app/realtime/operator_key.py), a scripted one in the tests."""
from __future__ import annotations

from typing import Callable, Protocol

END_REASON = "operator_stop"


class OperatorInput(Protocol):
    def poll(self) -> bool:
        """True when the operator asked to stop since the last poll (never blocks)."""
        ...


class OperatorStop:
    def __init__(self, source: OperatorInput, neutral: Callable[[], None], event: Callable[..., None]) -> None:
        self._source = source
        self._neutral = neutral
        self._event = event
        self.stopped_at: float | None = None  # race time of the stop

    def check(self, t_race: float) -> str | None:
        """Called once a tick at race time ``t_race``: END_REASON once the operator asked to stop, else None."""
        if self.stopped_at is None:
            if not self._source.poll():
                return None
            self.stopped_at = t_race
            self._neutral()
            self._event("stop", "operator stop key - all cars neutral", t_race=t_race)
        return END_REASON

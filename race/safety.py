"""The safety-hold state machine of the race loop (docs/race-stack.md, "Safety holds").

Each rule (a lost car, a non-finite state, a failed or stale plan, an invalid command, a corrupt
serial stream) is a named hold the loop sets or clears every tick. Setting a hold sends neutral to
every car at once and logs ``fault: <message> - all cars neutral``; clearing one logs ``recovered``
(``- racing again`` when it was the last). Holds that last ``stop_after_s`` without a break stop the
race: nothing would end it by itself any more (cars lost and coasting, planner dead)."""
from __future__ import annotations

from typing import Callable


class SafetyHolds:
    def __init__(self, neutral: Callable[[], None], event: Callable[[str, str], None], stop_after_s: float) -> None:
        self._neutral = neutral
        self._event = event
        self.stop_after_s = stop_after_s
        self.holds: dict[str, str] = {}       # key -> message of every active hold
        self._held_since: float | None = None  # start of the current unbroken stretch of holds

    def set(self, key: str, active: bool, message: str = "") -> None:
        if active and key not in self.holds:
            self.holds[key] = message
            self._neutral()
            self._event("fault", f"{message} - all cars neutral")
        elif not active and key in self.holds:
            del self.holds[key]
            self._event("recovered", f"{key} cleared" + ("" if self.holds else " - racing again"))

    def __bool__(self) -> bool:
        return bool(self.holds)

    def __len__(self) -> int:
        return len(self.holds)

    def stop_reason(self, now: float) -> str | None:
        """Called once a tick: the stop text when holds have lasted longer than stop_after_s, else None."""
        if not self.holds:
            self._held_since = None
        elif self._held_since is None:
            self._held_since = now
        elif now - self._held_since > self.stop_after_s:
            return (f"cars held neutral for {now - self._held_since:.1f} s (limit {self.stop_after_s:g} s): "
                    f"{'; '.join(self.holds.values())} - race stopped")
        return None

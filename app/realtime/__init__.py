"""Wiring of the real-time race modes (docs/race-stack.md): the `race --hil` / hardware options and
their start-up (``run``), the hardware-in-the-loop world (``hil``), the hardware camera feed
(``hardware``) and the loop bench (``bench``). The loop itself is ``race.loop``."""

"""The race engine: set-up, planning step, real-time loop, referee, recorder and recording reader,
shared by the simulated, HIL and hardware races (docs/race-stack.md). `app/` is the CLI around it."""

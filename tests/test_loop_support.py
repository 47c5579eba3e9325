"""Helpers shared by the real-time stack tests (imported explicitly, not a pytest conftest)."""
from __future__ import annotations

import argparse
import json


def race_parser():
    from app.commands import race, review

    parser = argparse.ArgumentParser(prog="python -m app")
    sub = parser.add_subparsers(dest="command")
    race.register(sub)
    review.register(sub)
    return parser


def run_cli(argv: list[str]) -> int:
    """Run `race`/`review` like app.cli.main does (UserError/ValueError -> exit code 2)."""
    from app.cli import UserError

    args = race_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (UserError, ValueError) as exc:
        raise SystemExit(f"error: {exc}") from exc


def neutral_at(events: list[dict], t: float) -> bool:
    """Were all cars neutral at the box at race time t? (last cars_neutral/cars_driving before t;
    neutral before the first command, as the box is)."""
    state = True
    for e in events:
        if e["time_s"] > t:
            break
        if e["kind"] == "cars_neutral":
            state = True
        elif e["kind"] == "cars_driving":
            state = False
    return state


def neutral_within(events: list[dict], t0: float, t1: float) -> bool:
    """Did every car become (or was it already) neutral at the box between race times t0 and t1?"""
    return neutral_at(events, t0) or any(e["kind"] == "cars_neutral" and t0 <= e["time_s"] <= t1 for e in events)


def load_json(path) -> dict:
    with open(path) as f:
        return json.load(f)

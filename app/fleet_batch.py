"""`python -m app batch --cars rd3g,mpc,mpc,mpc`: a fleet batch (docs/racing.md, "Fleet batch").

Each seed is raced twice with the same roster, grid and seed: as given (the RD3G car plans with
RD3G) and as its counterfactual (that car's planner swapped to MPC, everything else equal: name,
top speed, slot, ids). The RD3G car's finishing positions in the two are paired by seed. Jobs run
through app.commands.batch.run_races (local, process pool or Dask), one race per job."""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from app.cli import UserError

FLEET_CELLS = (("fleet", "rd3g"), ("fleet", "counterfactual"))
DEFAULT_FLEET_RACES = 100


def fleet_roster(roster, arm: str):
    """The roster of one arm: as given ("rd3g") or with the RD3G car's planner swapped to MPC."""
    if arm == "rd3g":
        return roster
    return tuple(dataclasses.replace(c, planner="mpc") if c.planner == "rd3g" else c for c in roster)


def the_rd3g_car(roster) -> str:
    """The one RD3G car of a fleet batch's roster (UserError otherwise)."""
    rd3g = [c.name for c in roster if c.planner == "rd3g"]
    if len(rd3g) != 1:
        raise UserError(f"--cars: a fleet batch compares one RD3G car with its MPC counterfactual; "
                        f"the roster has {len(rd3g)} RD3G cars")
    humans = [c.name for c in roster if c.planner == "human"]
    if humans:
        raise UserError(f"--cars: car {humans[0]}: planner: human drives real cars only")
    return rd3g[0]


def fleet_record(setup, outcome, cell, seed: int, car: str) -> dict:
    """One race of a fleet batch as a small picklable record: the followed car's position (unfinished:
    last, len(roster)), whether any car was unfinished, its at-fault contacts, every contact."""
    s = outcome.summary()
    mine = next(c for c in s["cars"] if c["name"] == car)
    return {"cell": cell, "seed": seed, "cars": len(setup.cars), "position": mine["finish_position"],
            "unfinished": any(c["finish_position"] is None for c in s["cars"]),
            "at_fault": int(mine["at_fault_collisions"]), "collisions": int(s["collisions"]),
            "rd3g_at_fault": int(s["rd3g_at_fault"]), "winner": s["winner"],
            "finishing_order": s["finishing_order"], "fallbacks": int(s["fallbacks"])}


def _ci95(d: np.ndarray) -> list[float] | None:
    """95 % t interval of the mean of paired differences d (None below two pairs)."""
    from scipy import stats

    if len(d) < 2:
        return None
    half = float(stats.t.ppf(0.975, len(d) - 1) * np.std(d, ddof=1) / math.sqrt(len(d)))
    return [float(np.mean(d)) - half, float(np.mean(d)) + half]


def summarise_fleet(records) -> dict:
    """The `fleet` JSON of a fleet batch: races (seeds), mean positions of the RD3G car and of its
    counterfactual (an unfinished car counts as last), their paired difference (RD3G minus
    counterfactual: negative = RD3G finishes ahead) with a 95 % t interval, win rates, the RD3G arm's
    at-fault contacts (the RD3G car's) and races with an unfinished car (either arm)."""
    arms = {arm: {r["seed"]: r for r in records if tuple(r["cell"]) == ("fleet", arm)} for _, arm in FLEET_CELLS}
    seeds = sorted(set(arms["rd3g"]) & set(arms["counterfactual"]))

    def position(r):
        return r["position"] if r["position"] is not None else r["cars"]

    ours = np.array([position(arms["rd3g"][s]) for s in seeds], dtype=float)
    theirs = np.array([position(arms["counterfactual"][s]) for s in seeds], dtype=float)
    d = ours - theirs
    mean = lambda v: float(np.mean(v)) if len(v) else None  # noqa: E731
    return {"races": len(seeds), "rd3g_mean_position": mean(ours), "counterfactual_mean_position": mean(theirs),
            "paired_difference": {"mean": mean(d), "ci95": _ci95(d)},
            "rd3g_win_rate": mean(ours == 1), "counterfactual_win_rate": mean(theirs == 1),
            "rd3g_at_fault": int(sum(arms["rd3g"][s]["at_fault"] for s in seeds)),
            "unfinished": int(sum(arms[a][s]["unfinished"] for s in seeds for a in arms)),
            "collisions": {arm: int(sum(arms[arm][s]["collisions"] for s in seeds)) for arm in arms}}


def fleet_table(f: dict, car: str) -> str:
    ci = f["paired_difference"]["ci95"]
    ci_text = "-" if ci is None else f"[{ci[0]:+.2f}, {ci[1]:+.2f}]"
    return "\n".join([
        f"| {car} planned by | races | mean position | win rate | collisions (all cars) |",
        "|---|---|---|---|---|",
        f"| RD3G | {f['races']} | {f['rd3g_mean_position']:.2f} | {f['rd3g_win_rate']:.2f} | {f['collisions']['rd3g']} |",
        f"| MPC (counterfactual) | {f['races']} | {f['counterfactual_mean_position']:.2f} | "
        f"{f['counterfactual_win_rate']:.2f} | {f['collisions']['counterfactual']} |",
        "",
        f"paired difference (RD3G minus counterfactual; negative = ahead): {f['paired_difference']['mean']:+.2f}, "
        f"95 % CI {ci_text}; {car} at fault in {f['rd3g_at_fault']} contact(s); races with an unfinished car: "
        f"{f['unfinished']}"])

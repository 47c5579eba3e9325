"""PNG figures for docs/racing.md: example races, one overtake (RD3G starts behind and passes) and one
block (RD3G starts in front on the slower car and keeps the faster MPC car behind), and a fleet race's
start grid (plot_grid)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from fileio import atomic_write_with
from race.recording import car_colors
from race.setup import grid_slots, start_states
from sim.collision import footprint_corners
from tracks import draw_track, load_track


def _clean(r, cell) -> bool:
    """An example race must be a clean RD3G win: both cars always on track, no contact."""
    return (tuple(r["cell"]) == cell and r["rd3g_won"] and "trace" in r and r["rd3g_off_track"] == 0
            and r["opponent_off_track"] == 0 and r["collisions"] == 0)


def _pick(records, cell, want):
    for r in records:
        if _clean(r, cell) and want(r["trace"][2]):
            return r
    return None


def _plot(rec, track, title: str, path: Path) -> Path:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t, states, progress = rec["trace"]
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(12, 4.2), gridspec_kw={"width_ratios": [1.6, 1]})
    draw_track(ax, track)
    for i, (name, cmap) in enumerate((("RD3G", "Reds"), ("MPC", "Blues"))):
        ax.scatter(states[:, i, 0], states[:, i, 1], c=t, cmap=cmap, s=4, label=name)
    ax.set_aspect("equal")
    ax.legend(loc="upper right")
    ax.set_title(f"{title} (seed {rec['seed']}; darker = later)")
    ax2.plot(t, progress[:, 0] - progress[:, 1], color="k")
    ax2.axhline(0, color="grey", lw=0.8)
    ax2.set_xlabel("time (s)")
    ax2.set_ylabel("RD3G progress minus MPC progress (m)")
    ax2.set_title("lead along the track")
    fig.tight_layout()
    atomic_write_with(path, lambda tmp: fig.savefig(tmp, dpi=110, format="png"))
    plt.close(fig)
    return path


def plot_examples(records, args, folder: Path) -> list[Path]:
    track = load_track(args.track)
    out = []
    overtake = _pick(records, ("rear", "fast"), lambda p: (p[0, 0] - p[0, 1]) < 0 < (p[-1, 0] - p[-1, 1]))
    if overtake:
        out.append(_plot(overtake, track, "Overtake: RD3G (faster) starts behind", folder / "race_overtake.png"))
    # The block with the closest attack: the smallest lead RD3G kept while the faster MPC car was behind.
    # A block: RD3G stays ahead the whole race.
    blocks = [r for r in records if _clean(r, ("front", "slow")) and np.all(r["trace"][2][:, 0] > r["trace"][2][:, 1])]
    if blocks:
        best = min(blocks, key=lambda r: float(np.min(r["trace"][2][:, 0] - r["trace"][2][:, 1])))
        out.append(_plot(best, track, "Block: RD3G (slower) starts in front", folder / "race_block.png"))
    return out


def plot_grid(setup, path: Path) -> Path:
    """The start grid of a race set-up (race.setup.start_states): each car's footprint in its colour
    (race.recording.car_colors), labelled with its name and grid slot, on the part of the track the
    grid covers (the start/finish line in red)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x0 = start_states(setup)
    g = setup.car.geometry
    corners = footprint_corners(x0[:, 0], x0[:, 1], x0[:, 2], g.footprint_length_m, g.footprint_width_m,
                                g.footprint_offset_m)
    slots = grid_slots(setup) if setup.grid != "single_file" else np.arange(len(x0))
    colors = car_colors(setup.names)
    fig, ax = plt.subplots(figsize=(8, 3.6))
    draw_track(ax, setup.track)
    for car, box, slot in zip(setup.cars, corners, slots):
        ax.fill(box[:, 0], box[:, 1], color=tuple(v / 255 for v in colors[car.name]), alpha=0.85,
                label=f"{car.name} ({car.planner}), slot {slot}")
        ax.annotate(str(slot), box.mean(axis=0), ha="center", va="center", fontsize=8, color="white")
    lo, hi = x0[:, :2].min(axis=0) - 0.35, x0[:, :2].max(axis=0) + 0.35
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    ax.legend(loc="center left", bbox_to_anchor=(1.01, 0.5), fontsize=8)
    ax.set_title(f"start grid ({setup.grid}, seed {setup.seed}): cars drive towards +x", fontsize=9)
    fig.tight_layout()
    atomic_write_with(path, lambda tmp: fig.savefig(tmp, dpi=100, format="png"))
    plt.close(fig)
    return Path(path)

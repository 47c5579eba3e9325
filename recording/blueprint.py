"""The default Rerun layout of a race recording: what the viewer shows when the .rrd is opened.

Entity paths are the race recordings' (docs/racing.md for the simulation, docs/race-stack.md for
HIL and hardware): ``world/track/*`` and ``world/cars/{car}/{footprint,plan,position,...}`` in track
metres, ``cars/{car}/...`` and ``planner/{car}/...`` scalars, ``loop/...`` timings and
``camera/{image,detections}`` of the real-time loop, ``race/events`` as text.
"""
from __future__ import annotations

from typing import Sequence

TRAIL_S = 3.0  # how much of each car's past path the trail view shows


def race_blueprint(car_names: Sequence[str], realtime: bool):
    """Blueprint of a race recording with cars ``car_names``; ``realtime`` (HIL and hardware) adds the
    camera image with its detections, the estimated speeds and the loop timing.

    Top row: the track from above (footprints, plans, positions; in real-time races also the camera's
    detections and the estimates), the same with every car's trail over the last TRAIL_S seconds of
    ``sim_time``, and the camera. Bottom row: speeds, commands, solve times (and loop timing), and the
    events as a text log.
    """
    import rerun.blueprint as rrb

    trail = rrb.VisibleTimeRange("sim_time", start=rrb.TimeRangeBoundary.cursor_relative(seconds=-TRAIL_S),
                                 end=rrb.TimeRangeBoundary.cursor_relative())
    top = [
        rrb.Spatial2DView(name="track", origin="world"),
        rrb.Spatial2DView(name=f"trails (last {TRAIL_S:g} s)", origin="world",
                          contents=["+ world/track/**"] + [f"+ world/cars/{c}/position" for c in car_names],
                          time_ranges=[trail]),
    ]
    speeds = [f"+ cars/{c}/speed_mps" for c in car_names]
    timing = [f"+ planner/{c}/solve_ms" for c in car_names]
    if realtime:
        top.append(rrb.Spatial2DView(name="camera", origin="camera", contents=["+ camera/image", "+ camera/detections"]))
        speeds += [f"+ cars/{c}/estimated_speed_mps" for c in car_names]
        timing += ["+ loop/period_ms", "+ loop/busy_ms", "+ loop/stage/**"]
    bottom = [
        rrb.TimeSeriesView(name="speeds (m/s)", origin="cars", contents=speeds),
        rrb.TimeSeriesView(name="commands", origin="cars", contents=[f"+ cars/{c}/command/**" for c in car_names]),
        rrb.TimeSeriesView(name="solve and loop times (ms)", origin="/", contents=timing),
        rrb.TextLogView(name="events", origin="race/events"),
    ]
    return rrb.Blueprint(rrb.Vertical(rrb.Horizontal(*top), rrb.Horizontal(*bottom), row_shares=[3, 2]),
                         collapse_panels=False)

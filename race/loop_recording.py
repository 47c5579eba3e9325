"""What the race loop writes to its recording (race.recording.RaceRecorder; entity paths in
docs/racing.md and docs/race-stack.md), kept out of the loop's control flow. :class:`LoopRecording`
writes; :class:`NoRecording` (no ``--out``) has the same methods and writes nothing. Loop timing is
recorded only by a real-time recorder (``RaceRecorder.realtime``): on a simulated clock the period is
the set one."""
from __future__ import annotations

import cv2
import numpy as np

from race.recording import record_car, record_plan


class NoRecording:
    path = None

    def event(self, t_race: float, kind: str, text: str, step: int) -> None:
        pass

    def plan(self, step: int, t_race: float, track, name: str, car_plan) -> None:
        pass

    def plan_lag(self, step: int, t_race: float, lag_ms: float) -> None:
        pass

    def tracking_errors(self, step: int, t_race: float, name: str, detection_mm: float,
                        estimate_mm: float | None) -> None:
        pass

    def tick(self, step: int, t_race: float, **_) -> None:
        pass

    def telemetry_time(self, step: int, t_race: float, ms: float) -> None:
        pass


class LoopRecording(NoRecording):
    """``rec``: the race's RaceRecorder; ``geometry``: the car file's (footprints); ``image_log_every``
    and ``image_downscale``: race.config.LoopConfig's."""

    def __init__(self, rec, geometry, image_log_every: int, image_downscale: int) -> None:
        self.rec, self.geometry = rec, geometry
        self.path = rec.path
        self.timing = getattr(rec, "realtime", True)
        self.image_log_every, self.image_downscale = image_log_every, image_downscale

    def event(self, t_race: float, kind: str, text: str, step: int) -> None:
        self.rec.event(t_race, kind, text, step=step)

    def plan(self, step: int, t_race: float, track, name: str, car_plan) -> None:
        record_plan(self.rec, step, t_race, track, name, car_plan.plan, car_plan.solve_ms)
        self.rec.scalar(f"planner/{name}/fallback", step, t_race, float(car_plan.plan.used == "fallback"))

    def plan_lag(self, step: int, t_race: float, lag_ms: float) -> None:
        self.rec.scalar("planner/plan_lag_ms", step, t_race, lag_ms)

    def tracking_errors(self, step: int, t_race: float, name: str, detection_mm: float,
                        estimate_mm: float | None) -> None:
        self.rec.scalar(f"tracking/{name}/detection_error_mm", step, t_race, detection_mm)
        if estimate_mm is not None:
            self.rec.scalar(f"tracking/{name}/error_mm", step, t_race, estimate_mm)

    def telemetry_time(self, step: int, t_race: float, ms: float) -> None:
        if self.timing:
            self.rec.scalar("loop/stage/telemetry_ms", step, t_race, ms)

    def tick(self, step: int, t_race: float, *, times: dict, stats, perceived, estimated: bool, sent: dict,
             holds: int, now: float, race_time, frames: int, render_ms, truth, t_truth) -> None:
        """One tick's rows: loop timing, estimates, commands, holds, the sensor reading (poses, camera
        image every ``image_log_every`` readings) and the cars' true states (``truth`` rows in roster order
        at race time ``t_truth``; rows with a non-finite value are left out)."""
        rec, k = self.rec, step
        if self.timing:
            if len(stats.period_ms):
                rec.scalar("loop/period_ms", k, t_race, stats.period_ms[-1])
            for name, ms in times.items():
                rec.scalar(f"loop/stage/{name}_ms", k, t_race, ms)
            rec.scalar("loop/busy_ms", k, t_race, stats.busy_ms[-1])
        if estimated:
            for name, st in perceived.states.items():
                rec.points(f"world/cars/{name}/estimate", k, t_race, st[:2])
                rec.scalar(f"cars/{name}/estimated_speed_mps", k, t_race, st[3])
        for name, (throttle, steer) in sent.items():
            rec.scalar(f"cars/{name}/command/throttle", k, t_race, throttle)
            rec.scalar(f"cars/{name}/command/steering_rad", k, t_race, steer)
        rec.scalar("loop/holds", k, t_race, holds)
        obs = perceived.observation
        if obs is not None:
            rec.scalar("camera/latency_ms", k, t_race, 1e3 * (now - obs.t_s))
            if obs.full_search is not None:
                rec.scalar("camera/full_search", k, t_race, float(obs.full_search))
            for ms in render_ms:
                rec.scalar("camera/render_ms", k, t_race, ms)
            for name, pose in obs.poses.items():
                rec.points(f"world/cars/{name}/detection", k, race_time(pose.t_s), [pose.x, pose.y])
                # the measured heading too: model identification (docs/sysid.md) needs whole poses
                rec.scalar(f"cars/{name}/detection_heading_rad", k, race_time(pose.t_s), pose.heading)
            if obs.image is not None and frames % self.image_log_every == 1:
                d = self.image_downscale
                small = cv2.resize(obs.image, None, fx=1.0 / d, fy=1.0 / d, interpolation=cv2.INTER_AREA)
                rec.image("camera/image", k, t_race, small)
                if obs.image_points is not None and len(obs.image_points):
                    rec.points("camera/detections", k, t_race, np.asarray(obs.image_points) / d)
        if truth is None:
            return
        for name, st in truth.items():
            if np.all(np.isfinite(st)):
                record_car(rec, k, t_truth, name, st, self.geometry)

"""Overhead-camera tracking: camera sources (real and synthetic), ArUco car markers, camera-to-track
calibration from fixed markers, and per-car EKF state estimation. See docs/tracking.md.

    from tracking.calibration import load_calibration
    from tracking.markers import ArucoTracker
    from tracking.estimator import MultiCarEstimator
"""

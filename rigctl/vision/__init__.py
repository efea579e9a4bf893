"""The camera side of the closed loop: tracker, calibration, the tracking loop."""

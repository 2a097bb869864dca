"""calib: polarizer calibration (mounting offset, per-shot angle errors)."""

"""Studies built on the core: the seed paper reproduced, simulation-based calibration."""

"""Studies built on the core: the paper's effective-origin search, the seed paper reproduced, campaigns,
simulation-based calibration."""

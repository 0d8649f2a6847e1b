"""Benchmarks that print figures: ``speed`` (one core), ``latency`` (the live node over DDS),
``robustness`` (global localization, kidnapping, long drive, corrupted input)."""

"""Scan-to-map matching: the correlative matcher behind the reference track and the calibrator
(offline tools; the node does not use it)."""
from __future__ import annotations

from localization.core.matching.correlative import CorrelativeMatcher, MatcherConfig, MatchResult, endpoints_base

__all__ = ["CorrelativeMatcher", "MatchResult", "MatcherConfig", "endpoints_base"]

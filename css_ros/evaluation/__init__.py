"""Offline evaluation: metrics, bag replay (`css_replay`) and its report."""

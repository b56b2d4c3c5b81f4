"""Agents: Gaussian assets of traffic participants (calibration, import and export)."""

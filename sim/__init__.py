"""Scenario files, ground-truth worlds and sensor simulation."""

"""Moved to :mod:`deploy.launch.conductor`; kept importable for the modules written before."""

from deploy.launch.conductor import Collected, Conductor, ConductorError, links_at, without_truth

__all__ = ["Collected", "Conductor", "ConductorError", "links_at", "without_truth"]

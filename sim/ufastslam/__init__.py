"""Worlds, measurements and world files of the Semantic UFastSLAM experiments."""

from sim.ufastslam.loader import bundled_worlds, load_world, parse_world
from sim.ufastslam.sensors import Frame, Run, simulate
from sim.ufastslam.world import RelationGroup, UWorld

__all__ = [
    "Frame",
    "RelationGroup",
    "Run",
    "UWorld",
    "bundled_worlds",
    "load_world",
    "parse_world",
    "simulate",
]

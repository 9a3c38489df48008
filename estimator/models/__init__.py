"""Models shared by the estimators and the simulator: SE(2), noise, classifier, sensor frames."""

from estimator.models.classifier import (
    AliasedClassifier,
    ClassifierModel,
    FirstComponents,
    paper_classifier,
    viewpoint,
)
from estimator.models.frames import Detection, SensorFrame
from estimator.models.noise import GaussianNoise

__all__ = [
    "AliasedClassifier",
    "ClassifierModel",
    "Detection",
    "FirstComponents",
    "GaussianNoise",
    "SensorFrame",
    "paper_classifier",
    "viewpoint",
]

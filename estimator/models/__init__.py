"""Models shared by the estimators and the simulator: SE(2), noise, classifier, sensor frames."""

from estimator.models.classifier import (
    AliasedClassifier,
    ClassifierModel,
    FirstComponents,
    paper_classifier,
    viewpoint,
)
from estimator.models.frames import MAX_STEP, ROBOT_ID, ROBOT_ID_RULE, Detection, SensorFrame
from estimator.models.learned import LearnedClassifier
from estimator.models.noise import GaussianNoise

__all__ = [
    "MAX_STEP",
    "ROBOT_ID",
    "ROBOT_ID_RULE",
    "AliasedClassifier",
    "ClassifierModel",
    "Detection",
    "FirstComponents",
    "GaussianNoise",
    "LearnedClassifier",
    "SensorFrame",
    "paper_classifier",
    "viewpoint",
]

"""Models shared by the estimators and the simulator: SE(2), noise, classifier, sensor frames."""

from estimator.models.classifier import (
    AliasedClassifier,
    ClassifierModel,
    FirstComponents,
    paper_classifier,
    viewpoint,
)
from estimator.models.frames import (
    GLOBAL_IDS,
    ID_KINDS,
    LOCAL_IDS,
    MAX_STEP,
    NO_ID,
    NO_IDS,
    ROBOT_ID,
    ROBOT_ID_RULE,
    Detection,
    SensorFrame,
    check_id_kind,
)
from estimator.models.learned import LearnedClassifier
from estimator.models.noise import GaussianNoise

__all__ = [
    "GLOBAL_IDS",
    "ID_KINDS",
    "LOCAL_IDS",
    "MAX_STEP",
    "NO_ID",
    "NO_IDS",
    "ROBOT_ID",
    "ROBOT_ID_RULE",
    "AliasedClassifier",
    "ClassifierModel",
    "Detection",
    "FirstComponents",
    "GaussianNoise",
    "LearnedClassifier",
    "SensorFrame",
    "check_id_kind",
    "paper_classifier",
    "viewpoint",
]

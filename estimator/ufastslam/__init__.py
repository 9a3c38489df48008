"""Semantic Unscented FastSLAM (design doc semantic-ufastslam.md): the scaled unscented
transform, the vectorised particle filter and the landmark relations."""

from estimator.ufastslam.filter import (
    AcceptedRelation,
    Observation,
    StepReport,
    UFastSLAM,
    UFastSLAMConfig,
    systematic_resample,
)
from estimator.ufastslam.relations import (
    GroupLabel,
    RelationConfig,
    RelationError,
    parse_label,
)
from estimator.ufastslam.unscented import UTParams

__all__ = [
    "AcceptedRelation",
    "GroupLabel",
    "Observation",
    "RelationConfig",
    "RelationError",
    "StepReport",
    "UFastSLAM",
    "UFastSLAMConfig",
    "UTParams",
    "parse_label",
    "systematic_resample",
]

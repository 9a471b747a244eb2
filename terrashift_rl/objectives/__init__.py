"""Losses: MA-POCA as a torchrl LossModule, and a running normaliser of value targets."""

from terrashift_rl.objectives.mapoca import MAPOCALoss, MAPOCAValueEstimator
from terrashift_rl.objectives.normalization import ValueNormalizer

__all__ = ["MAPOCALoss", "MAPOCAValueEstimator", "ValueNormalizer"]

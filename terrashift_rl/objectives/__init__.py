"""Losses: MA-POCA as a torchrl LossModule."""

from terrashift_rl.objectives.mapoca import MAPOCALoss, MAPOCAValueEstimator

__all__ = ["MAPOCALoss", "MAPOCAValueEstimator"]

"""The loggers the ``logger`` settings name (torchrl's), and logging an iteration's metrics.
wandb's own terminal output (its banner, its summary of every metric) is switched off: the run
says in one line where its logs are."""

from __future__ import annotations

import logging
import os
from pathlib import Path

from torchrl.record.loggers import Logger

from terrashift_rl.training.settings import LoggerConfig

__all__ = ["close_logger", "log_scalars", "logger_run_id", "make_logger"]

log = logging.getLogger(__name__)


def make_logger(
    config: LoggerConfig, name: str, run_dir: Path, run_id: str | None
) -> Logger | None:
    """The logger ``config`` names for the run ``name``, writing under ``run_dir``; ``run_id``
    continues a wandb run."""
    if config.kind == "none":
        return None
    if config.kind == "csv":
        from torchrl.record.loggers import CSVLogger

        return CSVLogger(name, log_dir=str(run_dir / "logs"))
    if config.kind == "tensorboard":
        from torchrl.record.loggers import TensorboardLogger

        return TensorboardLogger(name, log_dir=str(run_dir / "logs"))
    import wandb
    from torchrl.record.loggers import WandbLogger

    return WandbLogger(
        name,
        offline=config.mode == "offline",
        save_dir=str(run_dir),
        project=config.project,
        id=run_id,
        resume="allow",
        log_env_packages=False,
        settings=wandb.Settings(silent=True, console="off"),
    )


def log_scalars(logger: Logger | None, metrics: dict[str, float], step: int) -> None:
    """Logs every metric at ``step`` (env-steps), unless there is no logger."""
    if logger is not None:
        for name, value in metrics.items():
            logger.log_scalar(name, value, step=step)


def logger_run_id(logger: Logger | None) -> str | None:
    """The id of the logger's run (wandb's), which a resumed run continues."""
    return getattr(getattr(logger, "experiment", None), "id", None)


def close_logger(logger: Logger | None) -> None:
    """Finishes the logger's run and says where it is (wandb's; the others need nothing)."""
    experiment = getattr(logger, "experiment", None)
    finish = getattr(experiment, "finish", None)
    if finish is None:
        return
    finish()
    if experiment.offline:
        folder = os.path.relpath(experiment.settings.sync_dir)
        log.info(f"wandb: offline run in {folder} (`wandb sync {folder}` uploads it)")
    else:
        log.info(f"wandb: {experiment.url}")

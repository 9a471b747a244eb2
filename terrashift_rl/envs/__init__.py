"""TorchRL environments built on the TerraShift simulator."""

from terrashift_rl.envs.terrashift import EVENT_KEYS, GROUP, PRIVILEGED, TerraShiftEnv

__all__ = ["EVENT_KEYS", "GROUP", "PRIVILEGED", "TerraShiftEnv"]

"""terrashift_rl: the TerraShift shape-display benchmark as TorchRL components."""

__version__ = "0.1.0"

"""The models' error, importable without torch (the command line names it before it loads torch)."""


class ModelConfigError(ValueError):
    """A network or training configuration value is out of range or inconsistent."""

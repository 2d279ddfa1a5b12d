"""The error type for bad user input: ``lerobot-cso`` prints its message as one line and exits non-zero."""


class UsageError(Exception):
    """Bad user input (unknown task, impossible count, conflicting output dir, ...)."""

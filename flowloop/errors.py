"""The one error type the core raises for bad input.

Its message is a single line meant for the user; adapters turn it into
Klipper's config/command errors or Moonraker's 400 answers unchanged.
"""


class FlowloopError(ValueError):
    """Bad input, explained in one line."""

"""The one error type the core raises for bad input.

Its message is a single line meant for the user; adapters turn it into
Klipper's config/command errors or Moonraker's 400 answers unchanged.
"""


class FlowloopError(ValueError):
    """Bad input, explained in one line."""


def option_message(section: str, option: str, message: str) -> str:
    """"Section [x], option y: message": the one format of flowloop's config
    errors (host.klipper_config.option_error raises it in klippy)."""
    return f"Section [{section}], option {option}: {message}"

"""The one exception type for bad input."""


class DataError(ValueError):
    """Bad input: the message is one line that names the problem."""

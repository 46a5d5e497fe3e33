"""The one exception type the command line turns into a one-line error message."""


class MnerfError(Exception):
    """A user-facing error: bad input, an incompatible checkpoint, a missing file.

    The message is one line that says what is wrong and, where it helps, what to do. The command
    line prints it as ``mnerf: error: <message>`` and exits with status 2, having written nothing.
    """


class ConfigError(MnerfError, ValueError):
    """A config file or override that cannot be applied (unknown key, wrong type, bad value)."""

"""The one exception type that reaches the user as a one-line message."""


class BlunfError(Exception):
    """A user-facing error. The message is one line and names the file or value at fault."""

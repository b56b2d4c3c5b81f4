"""Domain errors: user mistakes that the CLI reports as one line and exit code 2."""


class OmniscsError(Exception):
    """A mistake in the user's input or request: the message says what was wrong and what to do."""


class ValidationError(OmniscsError):
    """A scene or artifact on disk failed validation; the message names the file and field."""

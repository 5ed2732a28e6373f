"""The one exception type the command line turns into a single clear line (no traceback)."""


class GuidingError(Exception):
    """Bad input or an unusable environment; the message alone tells the user what to fix."""

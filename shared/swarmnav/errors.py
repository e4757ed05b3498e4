"""Exception types of the core, one per concern, all deriving from SwarmnavError."""


class SwarmnavError(Exception):
    """Base class: an error a user can act on (the CLI prints it without a traceback)."""


class ConfigError(SwarmnavError):
    """A scenario/config file is unreadable or invalid; the message names the field."""


class DatasetError(SwarmnavError):
    """A dataset directory is missing, malformed or of an unknown schema version."""

"""The one error every config reader raises."""


class ConfigError(ValueError):
    """A config file or value is wrong; the message names the file and the key."""

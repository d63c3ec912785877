"""Typed errors raised by library code; only the CLI turns them into messages and exit codes."""


class SlamError(Exception):
    """Base class of every error this package raises on purpose."""


class InputError(SlamError):
    """The input data (bag, folder, file) cannot be used as given. CLI exit code 2."""


class TopicError(InputError):
    """The requested topic is missing, or no topic was given and several fit."""


class ConfigError(SlamError):
    """A configuration file or override is invalid (unknown key, bad value, unknown plugin)."""


class PluginError(ConfigError):
    """A plugin could not be found or loaded."""


class BackendError(SlamError):
    """The back end could not take an update (e.g. GTSAM found the system indeterminate).
    The pipeline stops there and writes what it has; the CLI reports it."""

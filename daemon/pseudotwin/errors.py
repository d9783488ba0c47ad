"""The one small exception tree. Everything the CLI reports to a user derives from
:class:`PseudotwinError`; anything else escaping is a bug."""


class PseudotwinError(Exception):
    """Base of every error pseudotwin reports to its user."""


class ConfigError(PseudotwinError):
    """A configuration file or command-line setting is invalid."""


class DataError(PseudotwinError):
    """Input data is malformed, missing a sensor, or too sparse for the task."""


class ArtifactError(PseudotwinError):
    """A model artifact cannot be read, is of a newer format, or does not fit the twin."""


class NumericalError(PseudotwinError):
    """A kernel matrix could not be factorized even with the largest allowed jitter."""


class StateInUseError(PseudotwinError):
    """Another daemon or recorder runs on the same state dir (it may end: worth retrying)."""


class BrokerError(PseudotwinError):
    """The MQTT broker cannot be reached (a one-shot command; the daemon reconnects)."""


class FitError(PseudotwinError):
    """Training failed (e.g. no converging optimizer start)."""

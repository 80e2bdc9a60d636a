"""Exceptions of the package. Every failure the package reports is a :class:`CovoError`; every
warning about its input a :class:`CovoWarning`."""


class CovoError(Exception):
    """Base class of all errors raised by covo-gtsam."""


class ConfigError(CovoError):
    """Invalid configuration value or file."""


class DatasetError(CovoError):
    """A dataset folder or file is missing or malformed."""


class InputError(CovoError, ValueError):
    """Array inputs with wrong shapes, non-finite values or invalid covariances."""


class EstimationError(CovoError):
    """The relative pose could not be estimated."""


class InsufficientPairsError(EstimationError):
    """Fewer matched point pairs than the estimator needs."""


class DegenerateGeometryError(EstimationError):
    """The point pairs do not constrain all six degrees of freedom (e.g. collinear points)."""


class CovarianceError(EstimationError):
    """The pose covariance could not be computed or is not a valid covariance."""


class CovoWarning(UserWarning):
    """Input the package works around (e.g. ground-truth samples left out), and says so."""

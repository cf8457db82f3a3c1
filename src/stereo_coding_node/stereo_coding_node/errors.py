"""This package's errors: both derive from vgm_common's InvalidInput, so nodes catch
VgmError, report a diagnostic and keep serving."""

from vgm_common.errors import InvalidInput


class CodingError(InvalidInput):
    """Inputs that cannot be coded or decoded (shape, dtype, sizes that differ)."""


class KeyFileError(InvalidInput):
    """The thesis method's key file is missing, unreadable or does not fit the image."""

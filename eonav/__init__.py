"""eonav: passive electro-optical obstacle ranging for aircraft.

Implements, and improves on, the field-based obstacle-location algorithm of
P. K. A. Menon, G. B. Chatterji and B. Sridhar, "Electro-Optical Navigation for
Aircraft", IEEE Trans. Aerospace and Electronic Systems 29(3), 1993.
Equation numbers in comments, "eq. (n)", are the paper's own.

Rooms (docs/architecture.md): geometry, io, ranging, obstacles, nav, bus, sim, app. The math never imports the
transport (zenoh); the services (``eonav.services``) are thin wrappers.
"""
import logging

__version__ = "0.1.0"

logging.getLogger(__name__).addHandler(logging.NullHandler())


class EonavError(Exception):
    """Root of every error eonav raises on purpose (bad input, bad config, ...)."""


class InputError(EonavError, ValueError):
    """Input that does not meet the contract: the message says what was wrong and what was expected."""


__all__ = ["EonavError", "InputError", "__version__"]

"""urd: capture polarization images through glass and separate reflection from transmission."""

__version__ = "0.1.0"

"""The built-in systems under test, one file each, on a shared interface
(:mod:`jaxfalsify.suts.interface`); :mod:`jaxfalsify.sut` registers them."""

__all__ = []

"""afmid's version, in a module of its own: the modules that stamp it into their outputs import it from here, so
that ``afmid/__init__.py`` (which opens the Python front door, :mod:`afmid.api`, on first use) is imported by none
of them and no import cycle runs through the package."""

__version__ = "0.1.0"

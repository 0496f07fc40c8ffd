"""gradsep: gradient-domain rendering with illumination separation, reconstructed by an unsupervised network."""

from model import __version__

__all__ = ["__version__"]

"""gradsep: gradient-domain rendering with illumination separation, reconstructed by an unsupervised network."""

__version__ = "0.1.0"

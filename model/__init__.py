"""gradsep's ground floor: the frame contract, its constants and errors, reconstruction and inference."""

#: The distribution's version (pyproject.toml), recorded in rendered frames and exported models and shown by
#: ``gradsep --version`` and the service; defined here, at the bottom of the import graph, so no library module
#: needs the command-line package for it.
__version__ = "0.1.0"
